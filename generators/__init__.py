"""Data generators (plugins): record trajectories into rosbags and replay them into BOP datasets.

Generators import the core (:mod:`bopsurg`), never the reverse; they register under the
``bopsurg.generators`` entry-point group.
"""
