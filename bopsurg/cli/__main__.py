"""``python -m bopsurg.cli`` runs the ``bopsurg`` command."""

import sys

from bopsurg.cli.main import main

sys.exit(main())
