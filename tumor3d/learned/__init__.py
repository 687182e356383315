"""The learned segmentation method: per-pixel features, a boosted forest, one 3-D lesion.

:mod:`~tumor3d.learned.features` computes the features,
:mod:`~tumor3d.learned.forest` holds a trained forest as plain arrays and
predicts with numba, :mod:`~tumor3d.learned.segment` turns the probability
into a lesion, :mod:`~tumor3d.learned.review` says when to check it, and
:mod:`~tumor3d.learned.training` samples rows and trains (LightGBM, an
optional extra). The shipped models are read by :mod:`~tumor3d.learned.shipped`.
"""
