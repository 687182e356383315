"""Segmentation: which slices are abnormal and where the tumour is (spec sections 3-4).

:mod:`~tumor3d.segmentation.detect` (abnormal slices), :mod:`~tumor3d.segmentation.segment`
(the methods: paper, robust, learned, multi-Otsu peer), :mod:`~tumor3d.segmentation.fcm`
(the paper's fuzzy c-means), :mod:`~tumor3d.segmentation.lesion` (the patient's lesion
model), :mod:`~tumor3d.segmentation.given_segmentation` (a user's mask),
:mod:`~tumor3d.segmentation.caveats` and :mod:`~tumor3d.segmentation.review` (when a
human should check); :mod:`~tumor3d.segmentation.patient` is the segment-tumor stage's
core (one patient's segmentation and everything the stage stores of it). The learned
models live in :mod:`tumor3d.learned`.
"""
