"""Experiments: offline runs, the pool setting, the policy benchmark and its report."""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "bench": [
            "AUSE_VIEW_KEYS",
            "BenchConfig",
            "PolicySpec",
            "SETTINGS",
            "STREAM_ONLY",
            "SUMMARY_KEYS",
            "UncertaintyStudy",
            "fisherrf_uncertainty_maps",
            "parse_policies",
            "parse_value",
            "pool_curves",
            "rescore_ause",
            "run_bench",
            "study_views",
            "summarise",
            "uncertainty_study",
        ],
        "offline": ["EvalConfig", "run_offline"],
        "pool": [
            "POOL_POLICIES",
            "PoolConfig",
            "PoolResult",
            "PoolSplit",
            "SCHEDULES",
            "check_pool_params",
            "farthest_point_views",
            "make_pool_policy",
            "pose_only",
            "run_pool",
            "split_pool",
        ],
        "report": ["AUSE_CAVEAT", "TABLE_COLUMNS", "markdown", "parse_markdown_table", "write_report"],
    },
)
