"""``meniscope calibrate``: a scene fitted to the lab's own video by analysis by synthesis, with its report."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from service.calibration import LOOKED, WINDOWS
from service.errors import MeniscopeError, require_folder_of
from service.verbs import add_scene_option


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="fit a scene file to a lab recording (analysis by synthesis) and report what the video identifies",
        description="Estimate the fluid's roughness and reflectance, the light's direction, size and strength, "
        "the camera's exposure, black level, blur and noise, its elevation, the ROI's place in the frame and the "
        "artifact spheres from unlabeled lab video, jointly with the motion of the frames used; write the "
        "calibrated scene and, beside it, SCENE.calibration.json and SCENE.calibration.png.",
    )
    p.add_argument("recording", type=Path, help="lab recording (.cine or .avi)")
    add_scene_option(p)
    p.add_argument("--out", type=Path, required=True, help="calibrated scene to write (SCENE.json)")
    p.add_argument("--frames", type=int, default=12, help="frames whose motion is fitted (default 12)")
    p.add_argument(
        "--stack",
        type=int,
        default=120,
        help="frames spread over the recording for the median image and the noise (default 120)",
    )
    p.add_argument(
        "--windows",
        type=int,
        default=WINDOWS,
        help=f"whole windows held to Eq. 1 that choose along the ridge the single frames leave open, 0 to skip that "
        f"stage (default {WINDOWS}; each costs about a minute)",
    )
    p.add_argument(
        "--edge-rays",
        type=int,
        default=0,
        help="rays per pixel axis for the finest level's pixels where the frame steps sharply, 0 for none (default 0; "
        "8 narrows the light's angle towards a real camera's at several times the time: docs/calibration.md)",
    )
    p.add_argument(
        "--hold",
        action="append",
        default=[],
        metavar="PARAMETER",
        help="keep a parameter you measured at the --scene file's value instead of fitting it, by its name in the "
        "report (e.g. light.angle_deg, from the lamp's size and distance: the video cannot tell the sun's angle from "
        "the meniscus' curvature, docs/calibration.md); repeat for more",
    )
    cut = p.add_mutually_exclusive_group()
    cut.add_argument(
        "--ejection-hz",
        type=float,
        help="ejections per second, phase found from the data (d and p are fitted once per window "
        "between ejections; default: ejections detected from the video)",
    )
    cut.add_argument(
        "--ejections",
        type=Path,
        help="file of ejection frame indices (one per line) or CSV with a 'frame' or 'time_s' column",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.calibration.fit import SCHEDULE, calibrate, with_edge_rays
    from service.calibration.footage import read_footage
    from service.calibration.report import write_report
    from service.calibration.windows import spread

    if not 2 <= args.frames <= 200:
        raise MeniscopeError("--frames", f"must be between 2 and 200, got {args.frames}")
    if not 8 <= args.stack <= 5000:
        raise MeniscopeError("--stack", f"must be between 8 and 5000, got {args.stack}")
    if not 0 <= args.windows <= LOOKED:
        raise MeniscopeError("--windows", f"must be between 0 and {LOOKED}, got {args.windows}")
    if not 0 <= args.edge_rays <= 16:
        raise MeniscopeError("--edge-rays", f"must be between 0 and 16, got {args.edge_rays}")
    if args.ejection_hz is not None and not (math.isfinite(args.ejection_hz) and args.ejection_hz > 0):
        raise MeniscopeError("--ejection-hz", f"must be a positive number, got {args.ejection_hz}")
    require_folder_of(args.out)
    from service.calibration.parameters import free
    from service.scene import Scene

    try:
        free(tuple(args.hold))
    except ValueError as exc:
        raise MeniscopeError("--hold", str(exc)) from None

    guess = Scene.load(args.scene)
    footage = read_footage(args.recording, args.frames, args.stack, args.ejections, args.ejection_hz, args.windows)
    cal = calibrate(footage, guess, schedule=with_edge_rays(SCHEDULE, args.edge_rays), held=tuple(args.hold))
    doc, png = write_report(cal, footage, args.out)
    chosen = next((row for row in cal.ridge if row["chosen"]), None)
    ridge = (
        ""
        if chosen is None
        else f"; {len(footage.lab_windows)} windows kept the fitted scene"
        if chosen["parameter"] is None
        else f"; {len(footage.lab_windows)} windows moved it to {chosen['parameter']} {chosen['value']:.4g}"
    )
    held = f"; held at the guess's value: {', '.join(cal.held)}" if cal.held else ""
    moved = spread(cal.ridge)
    widest = max(moved, key=lambda name: moved[name]["offset_mm"], default=None)
    systematic = (
        ""
        if widest is None
        else f"; along {widest} the windows' offsets move {moved[widest]['offset_mm'] * 1e3:.2g} um (median), "
        "which this calibration leaves open"
    )
    print(
        f"{args.out}: calibrated in {cal.seconds:.0f} s, residual {cal.residual_before * footage.full_scale:.1f} "
        f"-> {cal.residual_after * footage.full_scale:.1f} DN RMS{ridge}{held}{systematic}; report {doc}, figure {png}"
    )
    return 0
