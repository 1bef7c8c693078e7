"""Pose estimators (plugins): a YOLOX-like detector and a GDR-Net-like pose head.

Estimators import the core (:mod:`bopsurg`), never the reverse; they register under the
``bopsurg.estimators`` entry-point group.
"""
