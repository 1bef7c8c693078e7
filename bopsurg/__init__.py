"""bopsurg: BOP metrics and formats, synthetic data and estimators for surgical 6D pose.

The core (this package) needs only numpy, scipy, pandas, OpenCV and tqdm:

- :mod:`bopsurg.metrics`: batched BOP pose errors (RE, TE, MSSD, MSPD, ADD, ADD-S, VSD).
- :mod:`bopsurg.bop`: BOP datasets and results, read and written as the BOP toolkit does.
- :mod:`bopsurg.evaluation`: matching, BOP19 average recall and the paper's error tables.
- :mod:`bopsurg.visibility`: visibility masks, visib_fract and scene_gt_info fields.

Plugins live in :mod:`bopsurg.generators` and :mod:`bopsurg.models` and register through
entry points (:mod:`bopsurg.plugins`); the core never imports them.
"""

from bopsurg._version import __version__

__all__ = ["__version__"]
