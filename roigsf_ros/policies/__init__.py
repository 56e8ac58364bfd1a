"""Keyframe policies: the contract, the simple rules and the stream NBV policies (registered on import)."""

from roigsf_ros.core.exports import lazy_exports

# The registry is complete once the package is imported: these modules register their policies.
from roigsf_ros.policies import rules, stream  # noqa: F401

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "base": [
            "KeyframeMap",
            "KeyframePolicy",
            "checked_keyframes",
            "make_policy",
            "parse_params",
            "parse_value",
            "policy_names",
            "policy_parameters",
            "register_policy",
            "unknown_parameters",
            "unknown_policy",
        ],
        "rules": ["AllFrames", "EveryN", "GausSlam"],
        "stream": [
            "CandidateWindow",
            "CloseFrontStream",
            "FisherRFStream",
            "NoveltyStream",
            "ROIFisherStream",
            "RECOMMENDED_STREAM",
            "RECOMMENDED_STREAM_MAPPER",
            "RECOMMENDED_STREAM_POLICY",
            "ROIGSurFisherStream",
            "RandomStream",
            "STREAM_POLICIES",
            "StreamNBVPolicy",
            "TRIGGERS",
            "split_lookahead",
        ],
    },
)
