"""The lowest layer: errors, atomic file output, the pinhole camera, the Frame type, configs, lazy exports, where the
package's own files are, the ROS domain id checked without ROS.
"""

from roigsf_ros.core.exports import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "camera": [
            "Intrinsics",
            "MAX_POSITION_M",
            "POSE_RIGID_TOL",
            "REPLICA_DEPTH_SCALE",
            "check_pose",
            "depth_points_w",
            "derive_size",
            "load_cam_params",
            "load_pose",
            "matrix_to_quat_xyzw",
            "pose_from_position_quat",
            "quat_xyzw_to_matrix",
            "save_cam_params",
        ],
        "config": [
            "Config",
            "UnknownFieldError",
            "annotation_words",
            "check_annotation",
            "check_field_value",
            "fits_annotation",
        ],
        "errors": ["InputError", "warn_once"],
        "exports": ["lazy_exports"],
        "fileio": [
            "atomic_dir",
            "atomic_path",
            "check_output_name",
            "OUTPUT_MARKS",
            "check_replaceable",
            "check_replaceable_file",
            "check_run_output",
            "check_writable",
            "deferred_interrupts",
            "nested_output",
            "read_json",
            "remove_stale_temporaries",
            "write_json",
        ],
        "frame": ["COLOUR_FLOAT_MAX", "Frame", "check_float_colour", "resize_frame", "spread_indices"],
        "package_files": ["CHECKOUT_ROOT", "PACKAGE", "package_path", "package_path_places", "share_folders"],
        "ros_domain": ["MAX_DOMAIN_ID", "check_domain_id", "domain_id_from_env"],
    },
)
