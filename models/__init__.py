"""Pose estimators (plugins): a YOLOX-like detector and a GDR-Net-like pose head.

- :mod:`bopsurg.models.detector`, :mod:`bopsurg.models.pose`: the two networks, their
  losses and geometry, in plain PyTorch (no torchvision).
- :mod:`bopsurg.models.train_detector`, :mod:`bopsurg.models.train_pose`: training
  (``bopsurg train``), on data from :mod:`bopsurg.models.data`.
- :mod:`bopsurg.models.estimator`: the ``gdrnet`` estimator (``bopsurg predict``), with the
  small model shipped in ``weights/``.

Estimators import the core (:mod:`bopsurg`), never the reverse; they register under the
``bopsurg.estimators`` entry-point group.
"""
