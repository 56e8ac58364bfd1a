"""Next-best-view scoring: the config, the view ROI, close-front, the scorer and the state kept between calls."""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "close_front": ["CloseFrontMemory", "close_front_gain", "observation_weight", "voxel_keys"],
        "config": ["MODES", "NBVConfig"],
        "roi": [
            "LUMA_RGB",
            "ViewROI",
            "VoxelView",
            "coverage_weight",
            "footprint_weight",
            "incidence_weight",
            "splat_roi",
            "view_roi",
            "voxel_texture",
            "voxel_visibility",
            "voxel_weight",
        ],
        "scorer": [
            "NBVResult",
            "NBVScorer",
            "UncertaintyMaps",
            "block_mean",
            "depth_error_ause",
            "downsampled",
            "fuse_scores",
            "information_gain",
            "rank_candidates",
            "rays_meet_box",
            "render_surfel_scalar",
            "surfel_variance",
            "train_fisher",
            "zscore",
        ],
        "state": [
            "CLOSE_FRONT_MODES",
            "PreparedScorer",
            "RenderRGBD",
            "ScoringState",
            "TrainFisherCache",
            "carry_rows",
            "match_surfels",
            "pose_keys",
            "running_h_train_fits",
        ],
        "warmup": ["WARMUP_INTRINSICS", "warm_up_kernels", "warm_up_once"],
    },
)
