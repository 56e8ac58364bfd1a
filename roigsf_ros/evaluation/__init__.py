"""Yardsticks: image metrics, mesh precision/recall/F, AUSE, render metrics of held-out frames."""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "metrics": [
            "COMPLETION_RATIO_TAU_M",
            "MIN_EVAL_SIDE",
            "MeshLike",
            "RenderMetrics",
            "RenderRGBDepth",
            "as_legacy_mesh",
            "ause",
            "check_eval_size",
            "check_gt_mesh",
            "colorize_depth",
            "depth_l1",
            "gt_visible_mask",
            "mesh_metrics",
            "psnr",
            "raycast_depth",
            "raycasting_scene",
            "render_metrics",
            "sample_surface",
            "save_comparison_strip",
            "ssim",
            "to_json_safe",
        ],
    },
)
