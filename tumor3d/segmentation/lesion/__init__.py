"""Patient-level hyperintense-lesion segmentation (the robust default of sections 2 and 3).

The paper decides every slice on its own histogram. On real thick-slice MR
this fails (measured on BraTS FLAIR emulated at 2 mm / 5 mm: 0-30 % of the
tumour slices flagged, no tumour segmented, see ``reports/segmentation.md``):
a slice histogram has too few pixels and too many overlapping tissues for
its modes to be counted. This module uses what a single slice cannot:

1. **Patient-pooled normal-tissue model.** The brain voxels of *all* slices,
   after an in-plane Gaussian smoothing of sigma ``smoothing_mm``
   (normalised inside the brain so the dark exterior does not leak in), give
   ``mu`` = median and ``sigma`` = 1.4826 MAD. A tumour occupies far less
   than half of the brain, and the median and the MAD have a 50 % breakdown
   point, so they describe normal tissue even when the tumour is large. The
   smoothing is the spatial regularisation: thin bright structures (cortical
   ribbon, vessels, the partial-volume rim of the brain) average down with
   their darker neighbours, a lesion of several millimetres keeps its
   intensity.
2. **Seeds outside the model.** Voxels whose smoothed intensity exceeds
   ``mu + seed_sigmas * sigma`` (FLAIR/T2/T1c lesions are hyperintense).
3. **3-D connectivity across the thick slices.** Seeds are labelled with
   26-connectivity over the stack (consecutive slices touch); a component
   counts only if it has at least ``min_region_mm2`` of area on at least
   ``min_slices`` consecutive-slice planes (consistency between neighbouring
   slices); with ``keep_largest`` only the largest such component is kept
   (one tumour, as the paper's method assumes).
4. **Boundary refinement at partial-volume edges.** A pixel mixing the lesion
   and normal tissue is lesion for more than half of its area when its
   intensity exceeds the midpoint ``(t + mu) / 2`` of the pure intensities
   (``t`` = median intensity of the seed component, linear partial-volume
   mixing). Every pixel is decided by this rule: the unsmoothed pixels above
   the midpoint within ``2 smoothing_mm`` of the seed component (in-plane,
   and on the slice just beyond each of its slices: the tip) and connected
   to it form the lesion; this undoes the blur of step 1 at the border.
   Then pixel rings are grown, ``boundary_mm`` wide, against the *local* lesion gray
   (oedema at the border is darker than the lesion's median), never below
   ``mu + floor_sigmas sigma`` (see :func:`_grow_local`).
   A lesion covering more than half of the brain is rejected (the model's
   premise is violated: see ``MAX_BRAIN_FRACTION``).
4b. **Satellites the lesion reaches.** With ``keep_largest``, a significant
   seed component other than the kept one joins the lesion when the
   refined lesion of step 4 touches it (26-connected); what joined is
   refined by the same rule, on its own, and added (repeated while another
   is reached, at most ``MAX_CANDIDATES`` times). The seeds were apart
   only because the tissue between them is below the seed level;
   the partial-volume rule decided that tissue is lesion, so lesion and
   satellite are one connected lesion. On FLAIR and T2 a satellite joins
   also when it comes within ``SATELLITE_MM`` (1 cm) of the refined lesion:
   foci less than 1 cm apart are one tumour by the usual convention, and
   the whole-tumour label of these sequences counts them (on FLAIR, a
   satellite joining by proximity alone must pass step 3e). Not on T1c:
   normal enhancing structures lie next to a tumour there. Measured on BraTS
   pat0005 FLAIR, whose tumour continues in satellites on slabs 13-15 and
   23-25 (2 mm / 5 mm): 3-D Dice 0.809 -> 0.831 (touching) -> 0.845
   (1 cm), Eq. 7 error -19.5 % -> -14.5 % -> -9.3 %, a like gain at every
   emulation phase and at 1 mm; the one other change is a 0.7 mL satellite
   touching the lesion of native pat0003 (28 % of it in the label, 3-D Dice
   0.897 -> 0.896; ``reports/segmentation.md``).
3b. **Is there a lesion at all: deep, not superficial.** Where the normal
   model fails without any lesion is at the brain's surface: extracerebral
   tissue left by an imperfect brain extraction (scalp fat on T1), the
   cortical ribbon, and slices cutting the vertex or the base obliquely
   (partial volume with CSF). A candidate component is kept only if it
   reaches the inner half of the brain: its 90th percentile of depth (its
   deepest tenth, a robust maximum; 3-D Euclidean distance to the outside of
   the brain mask, in mm, through the voxel spacing) reaches the median
   depth of the brain itself. Reason: the grey-matter mantle is about half
   of the brain's volume and forms its outer layer, so the outer half of
   the brain by depth is cortex and surface, and a surface structure stays
   in it; a tumour reaches deeper, even where it is based at the surface
   (an enhancing tumour at the cortex: most of it is outer, its deep edge
   is not). The rule is scale-free (it compares two depths of the same
   brain) and its threshold is not fitted; the percentile is the one that
   best separates the real tumours from the false candidates of
   ``../shared/data`` (``reports/segmentation.md``: the 75th percentile
   first used rejected a held-out cortical T1c tumour at 0.98 of the
   median depth). A purely superficial (cortical or extra-axial) lesion is
   not found: documented limitation.
3c. **Is there a lesion at all: asymmetric, not bilateral anatomy.** Normal
   anatomy is left-right symmetric, a tumour breaks the symmetry. When the
   left-right array axis is known (``lr_axis``, from the scan's affine), a
   seed counts for the decision only if no seed lies at its mirror position
   (tolerance ``SYMMETRY_TOLERANCE_MM`` for anatomical asymmetry and a
   slight roll of the head): ventricles on a CSF-bright image, a vertex cap
   or a scalp ring cancel out. The mirror is about the brain's mid-sagittal
   plane, estimated from the image (:func:`symmetry_plane`: the yaw and
   offset about which the slices best match their mirror image), not the
   array's middle: a head turned by 5-10 degrees in the scanner puts the
   plane's ends beyond the tolerance (measured on the clinical T1c turned by
   5-10 degrees: 44-186 mL of false lesion about the array's middle, 3-11 mL
   about the estimated plane, 3.2 mL as acquired; ``reports/segmentation.md``).
   A roll of the head (the plane tilted across the slices) is not modelled:
   the tolerance absorbs a few degrees. Steps 3 and 3b run on these
   asymmetric seeds; the lesion is then
   the full seed component holding the kept asymmetric core (so a tumour's
   part near the midline, within the tolerance of its own mirror, stays
   in). Measured: mirrored share of the tumour components 0.00-0.40, of the
   false candidates of the tumour-free volumes 0.74-1.00. A tumour whose
   mirror image is itself (symmetric about the midline) has no asymmetric
   seed: on FLAIR step 3f looks for it; on T2 and T1c it is lost.
3d. **A tumour crossing the midline (FLAIR).** A glioma crosses into the
   other hemisphere through the corpus callosum, deep: at the surface the
   falx separates the hemispheres. Its far part mirrors its near part, so
   step 3c keeps only what lies within ``SYMMETRIC_REGAIN_MM`` of the
   asymmetric core. On FLAIR the seeds of the brain's inner half (at least
   as deep as its median depth, as in step 3b, on a depth with no preferred
   side: :func:`_inner_half`) connected to the kept lesion through such
   seeds join it too; an asymmetric seed component reached that way is a
   satellite (step 4b). Nothing checks that what joins lies across the
   plane: mirrored deep seeds on the lesion's own side connected to it (a
   periventricular hyperintensity touching it) join as well. Step 3d needs
   step 3b's depth: it is off with ``reject_superficial=False``. FLAIR
   only: its CSF is dark, while the deep bilateral bright structures of T2
   (the ventricles) and T1c (choroid plexus, deep veins) would join
   (measured: T2 3-D Dice 0.898 -> 0.853, BraTS pat0003 T1c 0.832 ->
   0.791). Mirrored tissue is weaker evidence than an asymmetric core, so
   the part that joins is decided by the partial-volume rule of step 4
   alone, without its boundary rings. A lesion spanning both hemispheres
   spans the ventricles between them, so
   step 5b's enclosure test uses the lesion's extent without that part
   (taken before step 5 fills holes, so that a hole of that part does not
   widen it; satellites reached through it count).
   Measured (``reports/segmentation.md``, in-process harness): native BraTS
   pat0003 3-D Dice 0.896 -> 0.917, volume error -2.3 % -> +3.9 %; at 2 mm /
   5 mm 0.893 -> 0.908 at offset 2 and 0.906-0.908 at every emulation
   phase; the held-out FLAIR 0.925 -> 0.930 (2 mm / 5 mm, offset 2); no
   other case changes. Without the depth limit, the unlabelled raw TCGA
   FLAIR head gains 155 mL through its scalp; with it, 0.7 mL.
3e. **Is there a lesion at all: brighter than normal tissue's own outliers
   (FLAIR).** The seed level ``mu + seed_sigmas sigma`` leaves about 2 % of
   normal tissue above it, and normal FLAIR anatomy has regions a little
   brighter than the rest (the cerebellar cortex, the mesial temporal lobe);
   a bias field or a head's asymmetry can leave one side of them above the
   seed level without its mirror. Such a candidate is normal tissue's upper
   tail clustered in space: its seeds' gray levels are distributed as the
   normal model's tail beyond the seed level. A lesion is another
   population, brighter. A candidate is kept only if the median of its
   seeds' smoothed gray reaches the upper quartile of that tail
   (:data:`TAIL_QUANTILE`; ``mu + 2.53 sigma`` for ``seed_sigmas`` 2,
   :func:`normal_tail_level`): most of it lies where only a quarter of
   normal tissue's outliers do. A large tumour hides the problem: its own
   voxels widen ``sigma``. Measured (``benchmarks/pseudo_healthy.py``): real
   FLAIR brains made tumour-free by replacing the tumour with its mirror
   image (BraTS pat0004, pat0005) report 0 mL at 1 mm and at 2 mm / 5 mm;
   before, pat0004 reported 16.9 mL in the cerebellum at 1 mm and 8.6-14.1
   mL in the mesial temporal lobe at 2 mm / 5 mm. The tail's median would
   still keep 12.3 mL of its mesial temporal lobe; its 90th percentile would
   miss pat0005's spheres implanted at the gray of its oedema (up to 14 mL
   at 2 mm / 5 mm). The seeds judged are those of the lesion step 3c forms
   (its asymmetric core with the mirrored seeds near it; without a mirror
   plane, the whole seed component). A candidate rejected here may still
   join a kept lesion as its satellite (step 4b) when the refined lesion
   touches it: the partial-volume rule then decided that the tissue between
   is lesion. A satellite the lesion only comes near (within 1 cm) must pass
   this test: proximity alone is weaker evidence. Measured: an implanted
   sphere in the pseudo-healthy pat0004 took 12.7 mL of the mesial temporal
   lobe by proximity and no longer does (1 mm Dice 0.38 -> 0.88), and no
   labelled case changes at any emulation phase. Applying the test to
   touching satellites too lost a true satellite of BraTS pat0005 at four
   phases of five (3-D Dice 0.848-0.856 -> 0.829-0.834). The real FLAIR
   tumours' seeds lie at a median of 3.3-5.6 ``sigma`` (four cases, 1 mm and
   2 mm / 5 mm; the raw TCGA head 2.9-4.0), so no labelled case changes. Not
   on T2: its lesions are less conspicuous (the CSF, not the lesion, is the
   brightest tissue), and the raw TCGA T2's lesion seeds at 2.4-2.5
   ``sigma``: step 3e would lose it (6.1 mL found today). Not on T1c: its
   enhancing rim is 2-3 pixels thin, the smoothing of step 1 dilutes it, and
   its seeds lie just above the seed level (BraTS pat0005 T1c: a median of
   2.3 ``sigma``).
3f. **A lesion straddling the midline (FLAIR), when no other is found.** A
   lesion centred on the mid-sagittal plane (a glioma of the corpus
   callosum, a "butterfly" glioma, a lymphoma around the third ventricle) is
   its own mirror image: step 3c leaves it no asymmetric seed, and the
   volume was "no tumour found" (measured: 4.2 and 14 mL spheres implanted
   at the oedema's gray on the midline of the tumour-free FLAIR of
   ``benchmarks/pseudo_healthy.py``, Dice 0 at every place; with this step,
   4.2 mL spheres at seven places of eight at 2 mm / 5 mm, Dice 0.51-0.81,
   and all eight at 1 mm, 0.55-0.91). When no
   asymmetric lesion is kept, the seeds within ``SYMMETRY_TOLERANCE_MM`` of
   the plane (the band where step 3c cannot tell a voxel from its mirror)
   form components; one that is significant (step 3) within the band and
   holds seeds on both sides of the plane crosses it as one structure, and
   its whole seed component is the lesion if it passes steps 3b (deep) and
   3e (beyond the normal tail). Bilateral normal anatomy is paired, its two
   halves apart (ventricles, periventricular caps, the hemispheres' cortex
   with the falx and its CSF between them); what is continuous across the
   plane and bright on FLAIR (the pons, the vermis) is normal tissue's tail,
   which step 3e rejects. Only when nothing else is found, so no volume with
   an asymmetric lesion changes (every labelled case is identical at every
   emulation phase and at 1 mm). FLAIR only, as step 3d: on T2 and T1c deep
   bilateral bright structures lie at the midline (the third ventricle, the
   deep veins, the choroid plexus). Step 3f needs step 3b's depth: it is off
   with ``reject_superficial=False``. The real tumour-free FLAIR of
   ``benchmarks/pseudo_healthy.py`` (two brains, every emulation phase and 1
   mm) still gives 0 mL; that is little tumour-free FLAIR, said as such.
5. **Enclosed core.** Necrosis and cysts are dark on FLAIR and T1c but part of
   the whole tumour; holes of each slice's mask are filled, and so are dark
   cavities enclosed by the lesion *and the brain border* (a cavity that
   opens onto the brain surface is no hole in the plain sense): a
   component of ``brain & ~mask`` enclosed by ``mask | ~brain``, touching
   the lesion, whose median gray is below the normal median ``mu`` (fluid
   or necrosis, not parenchyma). On T1c this fills the necrotic core
   inside the enhancing rim. A dark asymmetric cavity lying mostly within
   the lesion's extent joins it too (5b, :func:`_asymmetric_cavity`; with
   its dark voxels near that asymmetric core, as in step 3c), and
   its wall is then decided as the lesion's border was around the seeds
   (5c, :func:`_cavity_wall`: the partial-volume rule of step 4 within the
   blur's reach of the cavity, then the boundary rings there). The
   enhancing rim of a necrotic T1c lesion is often too thin to seed away
   from its thickest part; once its core is known, the rim is the bright
   tissue around that core.
6. **T2 and CSF.** On T2 the CSF is brighter than the lesion; voxels above
   the CSF threshold are excluded from the seeds and the
   growth (they may still be enclosed and filled).

Lengths and areas are in mm and mm2, converted to pixels through the scan's
in-plane spacing (:func:`_pixel_lengths`; a significant area keeps its 1 mm pixel
count on coarser pixels, :func:`area_in_pixels`): the model regularises a scan
with 0.5 mm pixels as one with 1 mm pixels. The values were chosen on 1 mm BraTS
pixels, where they are the pixel counts they replaced (every figure there is
unchanged). Measured on the five labelled FLAIR / T2 cases at 2 mm / 5 mm,
resampled in-plane to 0.5 mm pixels (pooled slab Dice; ``reports/segmentation.md``,
section "Lengths and areas in mm"): mean 0.889 with the former pixel counts, 0.903 in mm
(1 mm: 0.907); the largest loss against 1 mm went from 0.046 (the T2) to 0.015.

No constant here is fitted to a case: ``seed_sigmas`` was chosen by
leave-one-case-out on the three BraTS FLAIR cases (see the report); the
others have the physical reasons given above.

The package holds the steps by concept: :mod:`~tumor3d.segmentation.lesion.normal`
(step 1 and the normal tail of step 3e), :mod:`~tumor3d.segmentation.lesion.candidates`
(steps 2 and 3 to 3f), :mod:`~tumor3d.segmentation.lesion.symmetry` (the mid-sagittal
plane and the mirror test of step 3c), :mod:`~tumor3d.segmentation.lesion.growth` (steps
4 and 4b), :mod:`~tumor3d.segmentation.lesion.cavity` (step 5),
:mod:`~tumor3d.segmentation.lesion.pixels` (lengths and areas in pixels),
:mod:`~tumor3d.segmentation.lesion.regions` (mask geometry) and
:mod:`~tumor3d.segmentation.lesion.model` (the steps in order). The public names are
importable from here.
"""


from __future__ import annotations

from tumor3d.segmentation.lesion.candidates import (
    DEPTH_GRID_MM,
    DEPTH_PERCENTILE,
    MAX_CANDIDATES,
    MIDLINE_LESIONS,
)
from tumor3d.segmentation.lesion.growth import LOCAL_SIGMA_MM, LOCAL_TRUNCATE, SATELLITE_MM
from tumor3d.segmentation.lesion.model import (
    LESION_DEFAULTS,
    MAX_BRAIN_FRACTION,
    LesionResult,
    lesion_params,
    patient_lesion,
    segment_hyperintense_lesion,
)
from tumor3d.segmentation.lesion.normal import (
    TAIL_QUANTILE,
    NormalModel,
    normal_model,
    normal_tail_level,
)
from tumor3d.segmentation.lesion.pixels import REFERENCE_PIXEL_MM2, area_in_pixels
from tumor3d.segmentation.lesion.symmetry import (
    PLANE_GRID_MM,
    PLANE_MAX_YAW_DEG,
    PLANE_SLICES,
    SYMMETRIC_REGAIN_MM,
    SYMMETRY_TOLERANCE_MM,
    MirrorPlane,
    left_right_axis,
    mirror_image,
    symmetry_plane,
)

__all__ = [
    "DEPTH_GRID_MM",
    "DEPTH_PERCENTILE",
    "LESION_DEFAULTS",
    "LOCAL_SIGMA_MM",
    "LOCAL_TRUNCATE",
    "MAX_BRAIN_FRACTION",
    "MAX_CANDIDATES",
    "MIDLINE_LESIONS",
    "PLANE_GRID_MM",
    "PLANE_MAX_YAW_DEG",
    "PLANE_SLICES",
    "REFERENCE_PIXEL_MM2",
    "SATELLITE_MM",
    "SYMMETRIC_REGAIN_MM",
    "SYMMETRY_TOLERANCE_MM",
    "TAIL_QUANTILE",
    "LesionResult",
    "MirrorPlane",
    "NormalModel",
    "area_in_pixels",
    "left_right_axis",
    "lesion_params",
    "mirror_image",
    "normal_model",
    "normal_tail_level",
    "patient_lesion",
    "segment_hyperintense_lesion",
    "symmetry_plane",
]
