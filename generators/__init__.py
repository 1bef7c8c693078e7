"""Data generators (plugins): record trajectories into rosbags and replay them into BOP datasets.

Generators import the core (:mod:`bopsurg`), never the reverse; they register under the
``bopsurg.commands`` (``record``, ``generate``), ``bopsurg.render_backends`` (PyBullet) and
``bopsurg.renderers`` (depth) entry-point groups.
"""
