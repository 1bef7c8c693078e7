"""The stages of the ``gdrnet`` estimator, in the order it runs them.

1. :mod:`.detect`: boxes of the objects in the image (or external boxes).
2. :mod:`.head`: the pose head's pose of each box (:class:`.head.HeadPoses`).
3. :mod:`.refine`: the needle's pose fitted to its segmenter masks, and to their depth points
   with RGB-D; re-crops where the needle runs past its box (:class:`.refine.Refinement`).
4. :mod:`.ends`: the needle-end check, which may turn a pose end for end.
5. The map into the dataset's model frame is the core's (:mod:`bopsurg.model_frames`, run by
   ``bopsurg predict``).

Each stage is built from its own section of :class:`bopsurg.models.predict_config.
PredictConfig`, takes the previous stage's output, returns its own typed result and keeps its
own counts (``stats``, ``report()``); no stage reads or edits another's state. The estimator
(:mod:`bopsurg.models.estimator`) composes them; each can run alone in a test or a bench.
"""
