"""2DGS surfels and their differentiable rasteriser (numba and torch backends) and Fisher.

The plain reference rasteriser every fast path is tested against is the module
:mod:`roigsf_ros.render.reference` (its ``rasterize_surfels`` has the fast one's signature).
"""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "fisher": [
            "ALL_PARAMS",
            "GEOMETRIC_PARAMS",
            "OUTPUTS",
            "fisher_diag",
            "fisher_per_surfel",
            "fisher_weighted_sum",
            "frustum_subset",
            "packed_jacobian",
        ],
        "numba_setup": [
            "KERNEL_LOCK",
            "PIN_ENV",
            "Kernels",
            "balanced_bounds",
            "configure_numba",
            "n_threads",
            "numba_available",
            "pin_workers",
            "pinned_workers",
            "prange",
            "set_numba_threads",
            "use_numba",
            "worker_ids",
        ],
        "rasterize": [
            "ALPHA_MAX",
            "ALPHA_MIN",
            "FILTER_INV_SQUARE",
            "NPACK",
            "PAIR_BUFFER_LIMIT",
            "Pairs",
            "Projection",
            "RenderOutput",
            "T_MIN",
            "TileBins",
            "bin_tiles",
            "camera_tensors",
            "composite_pairs",
            "numba_bins",
            "numba_forward",
            "numba_pairs",
            "pair_alpha_depth",
            "project_packed",
            "project_surfels",
            "rasterize_surfels",
            "render_map",
            "select_pairs",
        ],
        "surfels": [
            "PARAM_NAMES",
            "SH_C0",
            "SH_C1",
            "SurfelMap",
            "check_device",
            "depth_normals",
            "depth_to_points",
            "frame_from_normals",
            "ply_field_names",
            "quat_to_rotmat",
            "rotmat_to_quat",
            "sh_to_color",
            "surfels_from_rgbd",
        ],
        "vecmath": ["acos_unit", "exp_neg", "exp_nonpositive"],
    },
)
