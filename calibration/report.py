"""What `robonav calibrate solve` prints and writes: the table of methods and its JSON form."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from robonav.calibration.hand_eye import transform_error
from robonav.calibration.solve import MethodResult, Solution
from robonav.pipeline.transforms import PoseSpec


def x_name(setup: str) -> str:
    return "world_from_camera" if setup == "eye_to_hand" else "ee_from_camera"


def spread(methods: list[MethodResult]) -> dict[str, float]:
    """Largest pairwise difference between the OpenCV methods' answers (translation mm, rotation deg)."""
    pairs = [transform_error(a.x, b.x) for a, b in itertools.combinations(methods, 2)]
    if not pairs:
        return {"translation_mm": 0.0, "rotation_deg": 0.0}
    return {"translation_mm": max(p[0] for p in pairs), "rotation_deg": max(p[1] for p in pairs)}


def report_dict(solution: Solution, camera_id: str) -> dict[str, Any]:
    """The JSON written by `--json`."""
    opencv = [m for m in solution.methods if m.method != "refined"]
    final = solution.methods[-1]
    pose = PoseSpec.from_matrix(solution.x)
    out: dict[str, Any] = {
        "setup": solution.setup,
        "camera_id": camera_id,
        "result": {
            "transform": x_name(solution.setup),
            "position_m": list(pose.position_m),
            "quat_xyzw": list(pose.quat_xyzw),
            "reprojection_rms_px": solution.refinement.rms_px,
            "sigma_translation_mm": solution.refinement.x_translation_sigma_mm,
            "sigma_rotation_deg": solution.refinement.x_rotation_sigma_deg,
        },
        "seed_method": solution.seed_method,
        "methods": [_method_dict(m, solution.x) for m in solution.methods],
        "spread_of_opencv_methods": spread(opencv),
        "views": {"used": len(solution.used_views), "corners": solution.refinement.corners,
                  "skipped": {str(k): v for k, v in solution.skipped_views.items()}},
    }
    if solution.motion is not None:
        out["motion"] = {"max_rotation_deg": solution.motion.max_rotation_deg, "axis_spread": solution.motion.axis_spread}
    if final.error_vs_truth is not None:
        out["error_vs_truth"] = {"translation_mm": final.error_vs_truth[0], "rotation_deg": final.error_vs_truth[1]}
        best = min(opencv, key=lambda m: m.error_vs_truth[0] if m.error_vs_truth else np.inf)
        assert best.error_vs_truth is not None
        out["best_opencv_vs_truth"] = {"method": best.method, "translation_mm": best.error_vs_truth[0],
                                       "rotation_deg": best.error_vs_truth[1]}
    return out


def _method_dict(method: MethodResult, final_x: np.ndarray) -> dict[str, Any]:
    pose = PoseSpec.from_matrix(method.x)
    to_final = transform_error(method.x, final_x)
    out: dict[str, Any] = {
        "method": method.method, "position_m": list(pose.position_m), "quat_xyzw": list(pose.quat_xyzw),
        "reprojection_rms_px": method.reprojection_rms_px, "rotation_residual_deg": method.rotation_residual_deg,
        "translation_residual_mm": method.translation_residual_mm,
        "to_refined": {"translation_mm": to_final[0], "rotation_deg": to_final[1]},
    }
    if method.error_vs_truth is not None:
        out["error_vs_truth"] = {"translation_mm": method.error_vs_truth[0], "rotation_deg": method.error_vs_truth[1]}
    return out


def format_table(report: dict[str, Any]) -> str:
    """A plain-text table of every method, the spread, and the result."""
    has_truth = "error_vs_truth" in report
    header = ["method", "x [m]", "y [m]", "z [m]", "reproj [px]", "pose res [deg]", "pose res [mm]",
              "to refined [mm]", "to refined [deg]"] + (["vs truth [mm]", "vs truth [deg]"] if has_truth else [])
    rows = []
    for m in report["methods"]:
        row = [m["method"], *(f"{v:+.4f}" for v in m["position_m"]), f"{m['reprojection_rms_px']:.3f}",
               f"{m['rotation_residual_deg']:.3f}", f"{m['translation_residual_mm']:.2f}",
               f"{m['to_refined']['translation_mm']:.2f}", f"{m['to_refined']['rotation_deg']:.3f}"]
        if has_truth:
            row += [f"{m['error_vs_truth']['translation_mm']:.2f}", f"{m['error_vs_truth']['rotation_deg']:.3f}"]
        rows.append(row)
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(r, widths)))
             for r in [header, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    result = report["result"]
    s = report["spread_of_opencv_methods"]
    lines += [
        "",
        f"spread of the OpenCV methods: {s['translation_mm']:.2f} mm, {s['rotation_deg']:.3f} deg (largest pairwise)",
        f"{result['transform']} (refined from {report['seed_method']}): position_m "
        f"[{', '.join(f'{v:.5f}' for v in result['position_m'])}], quat_xyzw "
        f"[{', '.join(f'{v:.6f}' for v in result['quat_xyzw'])}]",
        f"reprojection RMS {result['reprojection_rms_px']:.3f} px over {report['views']['corners']} corners in "
        f"{report['views']['used']} views; 1-sigma {result['sigma_translation_mm']:.2f} mm, "
        f"{result['sigma_rotation_deg']:.4f} deg",
    ]
    for index, reason in report["views"]["skipped"].items():
        lines.append(f"view {index} skipped: {reason}")
    if has_truth:
        e, b = report["error_vs_truth"], report["best_opencv_vs_truth"]
        lines.append(f"error vs ground truth: {e['translation_mm']:.3f} mm, {e['rotation_deg']:.4f} deg "
                     f"(best OpenCV method, {b['method']}: {b['translation_mm']:.3f} mm, {b['rotation_deg']:.4f} deg)")
    return "\n".join(lines)
