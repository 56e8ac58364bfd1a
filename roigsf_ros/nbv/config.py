"""NBVConfig: every tunable of the NBV scorer (each field is a ROS parameter of the same name)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.render.fisher import ALL_PARAMS, GEOMETRIC_PARAMS, OUTPUTS

MODES = ("roi-gsurfisher", "roi-fisher", "close-front", "fisherrf")
"""Score modes: the method, its two ablations and the FisherRF baseline."""
ROI_MODES = ("roi-gsurfisher", "roi-fisher")
"""Modes that score the ROI's Fisher: the ones the terms beyond the paper (unseen, frontier, FisherRF) add to."""
BACKFACE_TESTS = ("none", "tsdf", "surfels", "unconfirmed")
"""Values of ``NBVConfig.unseen_backfaces``: how the unseen term tells a pixel that renders the back of a surface."""
UNSEEN_MEASURES = ("pixels", "area", "cells", "rays")
"""Values of ``NBVConfig.unseen_measure``: what U(x) counts of the unseen pixels."""
UNSEEN_SOURCES = ("map", "carved")
"""Values of ``NBVConfig.unseen_source``: what tells an unseen pixel."""


@dataclass(frozen=True)
class NBVConfig(Config):
    """Every tunable of the NBV scorer; each field becomes a ROS parameter of the same name.

    Values the paper gives: the angle preferences, the 2.5 px footprint, epsilon, delta. The rest
    (beta, gamma, mu, phi, sigma_p, the bump widths, the texture test, occlusion) are our choices,
    each explained in its docstring.
    """

    mode: str = "roi-gsurfisher"
    """Score mode, one of :data:`MODES`."""
    epsilon: float = 0.4
    """Eq. 15 weight of z(F) (paper: 0.4); 0 drops the Fisher term (and skips its renders): an ablation."""
    delta: float = 0.6
    """Eq. 15 weight of z(I_vis) (paper: 0.6); 0 drops the close-front term: an ablation."""
    close_front_min_std: float = 0.01
    """Floor of the divisor of z(I_vis), in I_vis's units (1/m): ``(I - mean I) / max(std I, this)``. A numerical
    guard, not a change of method: candidates at the keyframes' own poses have I_vis exactly 0, but the same poses
    rounded to float32 gave gains of 1e-7 to 4e-5 1/m (rounding noise), which a plain z-score blew up to full strength
    and which then outweighed the Fisher term (a walk: another view chosen). A voxel seen frontally at 2 m weighs
    0.5 1/m and views that see new surface differ by hundreds, so 0.01 leaves every real spread as the paper z-scores
    it. 0: the plain z-score."""
    top_k: int = 5
    """Length of the ``top_k`` list of the result (the full ranking is always returned)."""

    # ---- Eq. 7: voxel weights
    beta: float = 1.0
    """Exponent of W_angle (paper: > 0, value not given); 1 keeps the bump's own width as the preference."""
    gamma: float = 1.0
    """Exponent of W_scale (paper: > 0, not given); 1, as beta."""
    mu: float = 1.0
    """Linear gain of W_cover (paper: >= 0, not given); 1 lets a once-seen voxel weigh up to 2x a well-fused one."""
    angle_pref_texture_poor_deg: float = 30.0
    """Preferred incidence angle on texture-poor surface (paper: about 30 deg)."""
    angle_pref_texture_rich_deg: float = 40.0
    """Preferred incidence angle on texture-rich surface (paper: about 40 deg)."""
    angle_sigma_deg: float = 15.0
    """Width of the incidence bump: 15 deg keeps frontal views (0 deg) at 0.14-0.37 and kills grazing ones."""
    footprint_pref_px: float = 2.5
    """Preferred projected voxel footprint in pixels (paper: about 2.5 px)."""
    footprint_sigma_ln: float = 0.693
    """Width of the footprint bump in ln units: ln 2, a footprint 2x off the preference weighs exp(-1/2)."""
    texture_radius_voxels: float = 2.0
    """Neighbourhood radius (voxels) of the surfel-colour texture test."""
    texture_max_neighbours: int = 16
    """Nearest surfels examined per voxel by the texture test."""
    texture_min_neighbours: int = 3
    """Fewer surfels than this near a voxel: texture-poor."""
    texture_std_threshold: float = 0.03
    """Luma std (colours in [0, 1]) from which a voxel is texture-rich: ~8/255, well above 8-bit noise."""

    # ---- voxel selection, visibility, splatting
    roi_max_abs_tsdf_voxels: float = 1.0
    """Near-surface band: |tsdf| within this many voxels (the TSDF module's default, one voxel)."""
    roi_min_weight: float = 1.0
    """Voxels need at least this TSDF weight (frames fused)."""
    near_m: float = 0.2
    """Near plane of candidate frusta and of the Fisher renders (2DGS's 0.2 m)."""
    far_m: float = 10.0
    """Far plane of candidate frusta and of the Fisher renders (the TSDF's default depth range)."""
    occlusion_tol_voxels: float = 2.0
    """Voxels more than this many voxels (plus a slant term) behind the z-buffer are occluded: the band is ~2 thick."""
    occlusion_min_cos: float = 0.5
    """Clamp of the incidence cosine in the occlusion tolerance's 1/cos slant factor (at most 2x, i.e. 60 deg)."""
    max_splat_radius_px: float = 8.0
    """Cap of the tent-kernel half-width; bounds the cost of very near voxels."""
    frontier_weight: float = 0.0
    """Beyond the paper: extra gain phi_f of frontier voxels in Eq. 7 (surface voxels next to never-observed space,
    :meth:`roigsf_ros.mapping.tsdf.TSDFVolume.frontier_mask`), W *= (1 + phi_f [frontier]) / (1 + phi_f), so the
    ROI pulls towards the edge of the mapped surface. 0: the paper's W (the ROI has no term for unseen space)."""

    # ---- Eq. 9-10, FisherRF, Eq. 17-18
    sigma_p: float = 1.0
    """Per-pixel noise scale of Eq. 9/18; a global scale cancels in the z-scores, only its ratio to phi matters."""
    phi: float = 1e-6
    """Prior of Eq. 10 (F / (H_train + phi)) and Eq. 17; FisherRF's lambda, so both methods share one prior."""
    fisherrf_lambda: float = 1e-6
    """FisherRF's log-prior regulariser (its default)."""
    fisher_outputs: tuple[str, ...] = ("color", "depth")
    """Rendered outputs of Eq. 9's f_p: colour and depth (RGB-D mapping; as the Mapper's h_train)."""
    fisher_params: tuple[str, ...] = GEOMETRIC_PARAMS
    """Geometric parameters of Eq. 9: means, quats (t_u, t_v) and log_scales (s_u, s_v)."""
    fisherrf_outputs: tuple[str, ...] = ("color",)
    """FisherRF's rendered output: the colour image."""
    fisherrf_params: tuple[str, ...] = ALL_PARAMS
    """FisherRF's parameters: all of them (sh_rest only where the map has it)."""
    fisher_downsample: int = 1
    """Candidate Fisher passes at 1/this resolution (ROI block-averaged, weights x this^2): a speed knob, 1 = exact."""
    close_front_exact: bool = False
    """How a kept scoring state (planner, stream policies) updates W_f of Eq. 12 when keyframes are added: True
    re-evaluates every keyframe pose on the current surface voxels (exact, O(keyframes x voxels) per update);
    False folds each new keyframe in once (:meth:`CloseFrontMemory.add_view`), so a voxel keeps what earlier
    keyframes gave it and one that enters the surface later gets only the newer keyframes' values."""

    # ---- beyond the paper (0 / off by default = the paper's method)
    unseen_weight: float = 0.0
    """Weight kappa of a third fused term ``kappa z(U(x))`` of the ROI modes, U(x) the fraction of the candidate's
    pixels where the map renders accumulated alpha below ``unseen_alpha`` (space the map has not seen; or the surface
    they can show, ``unseen_measure``). Not in the paper: its ROI and Fisher live only on already-mapped surface, so
    they cannot pull a room-scale map towards what it has not seen. 0: the paper's Eq. 15. With it on, a candidate
    that sees no mapped surface but unseen pixels is not flagged."""
    unseen_alpha: float = 0.5
    """Rendered alpha below which a pixel counts as unseen (GauS-SLAM's silhouette threshold)."""
    unseen_bbox_margin_m: float = 0.1
    """Only pixels whose ray meets the bounding box of the TSDF surface voxels, grown by this margin, count in
    U(x) (its denominator too): rays past the mapped region (background of an object-centric scene) are not
    unseen surface. A camera inside the box (a room) counts every pixel; inf: every pixel always counts."""
    unseen_backfaces: str = "none"
    """Also count in U(x) the pixels that render the *back* of the mapped surface: there the map has no surface
    facing this camera, only the far side of one, so what lies in front of it is unseen. 2DGS surfels render from
    both sides, so the alpha test alone counts such a pixel as seen: inside an open cabinet whose outside was mapped,
    the rays through the opening end on the back of its far wall (issue 10's cluttered scene). ``"tsdf"``: the
    rendered point lies in a TSDF surface voxel whose outward normal (toward the free space the fused views saw)
    faces away from the candidate; ``"surfels"``: most of the pixel's alpha comes from surfels whose normal faces
    away (a surfel's normal faces the camera that seeded it, and keeps its side through the optimisation), which
    also holds for boards thinner than the TSDF's truncation; ``"unconfirmed"``: as ``"surfels"``, but not where a
    keyframe saw the pixel's point from this side, unoccluded in the map's render at the keyframe
    (:class:`~roigsf_ros.nbv.unseen.KeyframeDepths`): a shell thinner than the mapper's ``densify_depth_margin_m``
    (the inside of a bowl) stays mapped by its outside's surfels however often it is seen from inside, and
    ``"surfels"`` calls it unseen forever; ``"none"``: alpha only (not "off", which ROS parameters and YAML read as
    false)."""
    unseen_confirm_margin_m: float = 0.05
    """``unseen_backfaces="unconfirmed"``: a keyframe saw a point when the map's depth rendered at the keyframe lies
    within this of the point's (metres); the mapper's ``densify_depth_margin_m``, within which it seeds nothing new."""
    unseen_measure: str = "pixels"
    """What U(x) counts. ``"pixels"``: the fraction of the counted pixels that are unseen. ``"area"``: the unseen
    surface they can show, in m^2: each unseen pixel weighs (z / fx) (z / fy), its footprint on a plane facing the
    camera at depth z, with z the farthest the unseen surface can lie: where the ray leaves the box of
    ``unseen_bbox_margin_m`` (``far_m`` without surface voxels), or the rendered depth of a back face, in front of
    which the unseen surface lies. The mesh recall counts surface by area, so a far view of an unseen wall shows
    more of it than a near one, which the pixel fraction scores the same. Needs a finite ``unseen_bbox_margin_m``.
    ``"cells"`` (``unseen_source="carved"`` only): the distinct carved cells where the unseen pixels' rays enter their
    unknown stretch, times ``unseen_voxel_m``^2 (m^2): the boundary of unobserved space the view looks at, each part
    once whatever its distance, where the pixel fraction counts a near pocket by the pixels it fills and the area
    count weighs a ray by where its stretch ends. A camera standing in space no keyframe observed counts only the
    few cells its rays start in, so the count favours views from observed space, as frontier exploration does.
    ``"rays"`` (``unseen_source="carved"`` only): each unseen pixel weighs the length of its unknown stretch in cells
    of ``unseen_voxel_m`` (camera z), summed over the counted pixels and divided by their number: the unknown voxels
    each ray crosses, the volumetric information gain of active reconstruction (Isler et al. 2016, Delmerico et al.
    2018), where the pixel fraction counts a ray that crosses one cell of unobserved space as one that crosses a
    room. A few uncarved cells in front of surface seen from another side then weigh little."""
    unseen_source: str = "map"
    """What tells an unseen pixel. ``"map"``: the map's render (alpha below ``unseen_alpha``, and the back faces of
    ``unseen_backfaces``). ``"carved"``: the pixel's ray reaches observed surface (or the box's side) through space
    no keyframe observed, in a grid of ``unseen_voxel_m`` cells over the box of ``unseen_bbox_margin_m``, carved
    from the map's depth rendered at every keyframe (:class:`~roigsf_ros.mapping.observed_space.ObservedSpace`;
    unknown space crossed before observed free space does not count). The far side of a surface seen from one side,
    and what lies behind an object no keyframe looked past, are then unseen without a back-face test
    (``unseen_backfaces`` is not used), and a hole in the map that keyframes saw through counts as seen;
    ``unseen_measure="area"`` takes z where the unknown stretch ends. Needs a finite ``unseen_bbox_margin_m``."""
    unseen_voxel_m: float = 0.025
    """``unseen_source="carved"``: the cell size of the carved grid (metres); 2.5 cm was chosen over 5 cm on the two
    tuning scenes (a gap between objects a cell or two wide is carved only where the cells happen to fall)."""
    unseen_carve_rerender: bool = True
    """``unseen_source="carved"``, in a kept scoring state (planner node, stream and pool policies): True renders the
    map at every keyframe pose and carves the grid again at every scoring call, so a planner request grows with the map
    (12-13 ms per keyframe at 160x120 in ``roigsf perf nbv``: 2.3-2.7x the paper's request at 64 keyframes); False
    renders each keyframe once, when the state first sees it (as its TSDF fuses it), keeps that depth and carves only
    new keyframes into the kept grid (:class:`~roigsf_ros.nbv.state.CarvedSpaceMemory`; the kept depths are carved
    again, without rendering, when the box of the surface grows): 0.64-0.67x F2's request at 64 keyframes, level in
    recall on the tuning scenes and 0.0006 lower in F@5cm (docs/measured-figures.md). Not in the paper. A call
    without a kept state always renders."""
    unseen_min_stretch_m: float = 0.0
    """``unseen_source="carved"`` (pixels, area or rays): a pixel counts as unseen only where the unknown stretch its
    ray crosses last, before observed surface or the box's side, is at least this long (metres of camera z), or begins
    where the ray enters the box (it goes on outside, so its length is unknown). Not in the paper. Observed surface seen
    from another direction often has a cell or a few of uncarved space right in front of it along a new ray, so it reads
    as unseen. Measured on the sixth room (forty-second session, ``scripts/pick_regret.py --pixels``), picks 9-16: half
    of the unseen pixels that show no new surface look through fewer than 8 cells (0.2 m at 2.5 cm), 2 % of those that
    do; on the shelf, seen from outside its box, 43 % of those that do (hence the box-side exception). 0.2 passed the
    tuning scenes by noise and met no reported scene the variant misses (docs/measured-figures.md). 0: every unknown
    stretch counts (as before)."""
    unseen_min_std: float = 0.0
    """Floor of the divisor of z(U), in U's units (a fraction of the pixels, m^2 with ``unseen_measure`` area or cells,
    cells per pixel with rays): ``kappa (U - mean U) / max(std U, this)``. Late in a run the candidates' U differ by a
    few pixels, and a plain z-score makes that difference as strong as the Fisher and close-front terms; with a floor, a
    spread below it counts for less, so those terms decide once little unseen space is left. 0: the plain z-score."""

    unseen_plan_views: int = 1
    """Views the unseen term plans over (``unseen_source="carved"``, ``unseen_measure="pixels"``): with k > 1, U(x)
    is the unseen pixel fraction that x and the k - 1 other candidates a greedy completion adds after it would show
    together, each carved cell where unseen rays enter counted once per plan (:mod:`roigsf_ros.nbv.plan`), so a
    candidate whose unseen space others also see weighs less than one that sees what no other candidate does. 1: the
    candidate's own fraction (myopic, as every session before the thirty-sixth)."""
    unseen_rarity: float = 0.0
    """Exponent beta of the rarity weight of U (``unseen_source="carved"``, ``unseen_measure`` pixels or rays): each
    unseen pixel's weight in U (1, or its stretch in cells) is divided by n^beta, n the number of this scoring call's
    candidates whose unseen pixels enter the carved grid's unknown space in the same block of
    ``unseen_rarity_block_m`` (:func:`~roigsf_ros.nbv.plan.rarity_weighted`). Not in the paper: the frequency weight
    of greedy set cover. A greedy pick puts off the view that alone sees some pocket while views with bigger but
    replaceable gains go first, and runs out of views (the hindsight study of docs/measured-figures.md: swapping a few
    of the greedy views meets targets the greedy pick misses); unseen space every candidate looks into then weighs
    1/M, space only one looks into its full weight. 0: each pixel its own weight (as before)."""
    unseen_rarity_block_m: float = 0.1
    """``unseen_rarity`` > 0: the side of the blocks (metres, rounded to whole ``unseen_voxel_m`` cells) within which
    rays from different candidates count as looking into the same unseen space."""
    fisherrf_weight: float = 0.0
    """Weight kappa_r of one more fused term of the ROI modes, ``kappa_r z(R(x))``, R(x) the candidate's FisherRF score
    exactly as mode ``fisherrf`` computes it (its own H_train over ``fisherrf_params`` and ``fisherrf_outputs``,
    ``fisherrf_lambda``), z over the same candidates as the other terms. Not in the paper: once the unseen term has
    little left to find, the paper's two terms rule the pick, and FisherRF's score (every parameter, whole image)
    added more late in a pool run (the forty-first session's question; it lost on the tuning scenes). Each call then
    also sums FisherRF's H_train over every keyframe pose, uncached. 0: no such term, nothing extra computed."""

    def uses_fisher(self, mode: str | None = None) -> bool:
        """Whether scoring in ``mode`` (None: this config's) needs the Fisher terms, hence H_train: not for
        close-front, nor for roi-gsurfisher with ``epsilon`` 0 (F weighs nothing in Eq. 15).
        """
        mode = mode or self.mode
        return mode != "close-front" and not (mode == "roi-gsurfisher" and self.epsilon == 0)

    def validate(self) -> NBVConfig:
        """Self, or InputError naming the first field out of range."""
        if self.mode not in MODES:
            raise InputError("mode", f"unknown score mode '{self.mode}' (choose from {', '.join(MODES)})")
        positive = ("beta", "gamma", "angle_sigma_deg", "footprint_pref_px", "footprint_sigma_ln")
        positive += ("texture_radius_voxels", "roi_max_abs_tsdf_voxels", "near_m", "sigma_p", "phi", "fisherrf_lambda")
        positive += ("unseen_confirm_margin_m", "unseen_voxel_m", "unseen_rarity_block_m")
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v > 0):
                raise InputError(name, f"must be a finite number > 0, got {v!r}")
        for name in (
            "epsilon",
            "delta",
            "close_front_min_std",
            "mu",
            "texture_std_threshold",
            "roi_min_weight",
            "occlusion_tol_voxels",
            "unseen_weight",
            "unseen_min_std",
            "unseen_min_stretch_m",
            "unseen_rarity",
            "frontier_weight",
            "fisherrf_weight",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v >= 0):
                raise InputError(name, f"must be a finite number >= 0, got {v!r}")
        if (
            self.mode == "roi-gsurfisher"
            and self.epsilon == 0
            and self.delta == 0
            and self.unseen_weight == 0
            and self.fisherrf_weight == 0
        ):
            raise InputError(
                "epsilon", "epsilon, delta, unseen_weight and fisherrf_weight are all 0: the fused score has no term"
            )
        for name in ("angle_pref_texture_poor_deg", "angle_pref_texture_rich_deg"):
            if not 0.0 <= getattr(self, name) < 90.0:
                raise InputError(name, f"must be in [0, 90) degrees, got {getattr(self, name)}")
        if not (np.isfinite(self.far_m) and self.far_m > self.near_m):
            raise InputError("far_m", f"must be finite and > near_m ({self.near_m}), got {self.far_m}")
        if not self.unseen_bbox_margin_m >= 0:
            raise InputError(
                "unseen_bbox_margin_m", f"must be >= 0 (inf: every pixel), got {self.unseen_bbox_margin_m}"
            )
        if not 0.0 < self.unseen_alpha <= 1.0:
            raise InputError("unseen_alpha", f"must be in (0, 1], got {self.unseen_alpha}")
        if not 0.0 < self.occlusion_min_cos <= 1.0:
            raise InputError("occlusion_min_cos", f"must be in (0, 1], got {self.occlusion_min_cos}")
        if not self.max_splat_radius_px >= 1.0:
            raise InputError("max_splat_radius_px", f"must be >= 1, got {self.max_splat_radius_px}")
        for name in ("close_front_exact", "unseen_carve_rerender"):  # a string such as "no" would read as true
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise InputError(name, f"must be true or false, got {getattr(self, name)!r}")
        if not self.unseen_carve_rerender and self.unseen_source != "carved":
            raise InputError("unseen_carve_rerender", "false keeps the carved grid: it needs unseen_source=carved")
        if self.unseen_backfaces not in BACKFACE_TESTS:
            raise InputError(
                "unseen_backfaces", f"must be one of {', '.join(BACKFACE_TESTS)}, got {self.unseen_backfaces!r}"
            )
        if self.unseen_measure not in UNSEEN_MEASURES:
            raise InputError(
                "unseen_measure", f"must be one of {', '.join(UNSEEN_MEASURES)}, got {self.unseen_measure!r}"
            )
        if self.unseen_measure == "area" and not np.isfinite(self.unseen_bbox_margin_m):
            raise InputError("unseen_measure", "area needs a finite unseen_bbox_margin_m (where an unseen ray ends)")
        if self.unseen_source not in UNSEEN_SOURCES:
            raise InputError("unseen_source", f"must be one of {', '.join(UNSEEN_SOURCES)}, got {self.unseen_source!r}")
        if self.unseen_measure in ("cells", "rays") and self.unseen_source != "carved":
            raise InputError(
                "unseen_measure", f"{self.unseen_measure} counts carved cells: it needs unseen_source=carved"
            )
        if self.unseen_source == "carved" and not np.isfinite(self.unseen_bbox_margin_m):
            raise InputError("unseen_source", "carved needs a finite unseen_bbox_margin_m (the box of the carved grid)")
        for name in ("top_k", "texture_max_neighbours", "texture_min_neighbours", "fisher_downsample",
                     "unseen_plan_views"):  # fmt: skip
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise InputError(name, f"must be a positive integer, got {getattr(self, name)!r}")
        if self.unseen_plan_views != 1 and (self.unseen_source != "carved" or self.unseen_measure != "pixels"):
            raise InputError(
                "unseen_plan_views", "plans over carved cells: it needs unseen_source=carved and unseen_measure=pixels"
            )
        if self.unseen_min_stretch_m > 0 and (
            self.unseen_source != "carved" or self.unseen_measure == "cells" or self.unseen_plan_views != 1
        ):
            raise InputError(
                "unseen_min_stretch_m",
                "measures the carved grid's unknown stretches: it needs unseen_source=carved, unseen_measure pixels, "
                "area or rays and unseen_plan_views=1",
            )
        grouped_by_cell = self.unseen_source == "carved" and self.unseen_measure in ("pixels", "rays")
        if self.unseen_rarity > 0 and (not grouped_by_cell or self.unseen_min_stretch_m > 0):
            raise InputError(
                "unseen_rarity",
                "weighs the carved grid's entry cells: it needs unseen_source=carved, unseen_measure pixels or rays "
                "and unseen_min_stretch_m=0",
            )
        for name in ("fisher_outputs", "fisherrf_outputs"):
            bad = [o for o in getattr(self, name) if o not in OUTPUTS]
            if bad or not getattr(self, name):
                raise InputError(name, f"unknown or no outputs {bad} (choose from {', '.join(OUTPUTS)})")
        for name in ("fisher_params", "fisherrf_params"):
            bad = [p for p in getattr(self, name) if p not in ALL_PARAMS]
            if bad or not getattr(self, name):
                raise InputError(name, f"unknown or no parameters {bad} (choose from {', '.join(ALL_PARAMS)})")
        return self


RECOMMENDED_UNSEEN: Mapping[str, float | str] = MappingProxyType(
    {"unseen_weight": 2.0, "unseen_source": "carved", "unseen_measure": "rays"}
)
"""The :class:`NBVConfig` fields of the variant the README recommends for choosing views among candidates (F3,
``roi-gsurfisher:unseen_weight=2:unseen_source=carved:unseen_measure=rays``): the paper's score plus 2 z(U_ray). Not
the default, which stays the paper's method; the kernel warm-up scores with it too, so its carved grid starts
compiled. Read-only: ``NBVConfig(**RECOMMENDED_UNSEEN)``, or ``{**RECOMMENDED_UNSEEN, ...}`` to change a field."""

__all__ = [
    "BACKFACE_TESTS",
    "MODES",
    "RECOMMENDED_UNSEEN",
    "ROI_MODES",
    "UNSEEN_MEASURES",
    "UNSEEN_SOURCES",
    "NBVConfig",
]
