"""The surfel mapper (optimisation, densify/prune, running H_train), its losses and the TSDF."""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "losses": [
            "SSIM_SIGMA",
            "SSIM_WINDOW",
            "colour_loss",
            "depth_l1",
            "depth_to_normal_cam",
            "distortion",
            "normal_consistency",
            "ssim",
            "ssim_map",
        ],
        "mapper": [
            "DEPTH_MODES",
            "H_TRAIN_FILE",
            "Keyframe",
            "MapMeta",
            "Mapper",
            "MapperConfig",
            "MapperStats",
            "depth_scale_note",
            "read_h_train",
            "read_map_meta",
            "valid_depth_mask",
            "write_h_train",
            "write_map_meta",
        ],
        "observed_space": ["FREE", "OCCUPIED", "UNKNOWN", "ObservedSpace"],
        "tsdf": ["SurfaceVoxels", "TSDFVolume", "canonical_mesh", "tsdf_mesh_from_depths"],
    },
)
