"""The calibration report beside the scene: every parameter before and after with its uncertainty, the
residual, the noise and the defects as JSON, and a PNG of lab frames beside their synthesis (the paper's
Figs. 7 and 15) over frames from several phases of the oscillation."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from service.calibration import parameters as P
from service.calibration.fit import Calibration, crop
from service.calibration.footage import Footage
from service.calibration.open_ranges import SCHEMA, report_paths
from service.calibration.profile import Profile
from service.calibration.synthesis import Synthesis
from service.calibration.truth import load_truth, score
from service.calibration.windows import spread
from service.plotting import pyplot

#: One sigma at or below which a parameter counts as identified by the video (file units; "rel": relative).
PRECISION: dict[str, tuple[float, str]] = {
    "fluid.roughness": (0.25, "rel"),
    "fluid.reflectance": (0.1, "abs"),
    "light.azimuth_deg": (1.0, "abs"),
    "light.elevation_deg": (1.0, "abs"),
    "light.angle_deg": (0.2, "rel"),
    "camera.exposure": (0.1, "rel"),
    "camera.elevation_deg": (0.5, "abs"),
    "sensor.blur_sigma_px": (0.2, "abs"),
    "sensor.offset": (0.01, "abs"),
}
#: Frames shown in the PNG.
SHOWN = 6


def _value(scene_dict: dict, name: str) -> float:
    section, key = name.split(".")
    return float((scene_dict.get(section) or {}).get(key, 0.0))


def profile_verdicts(profiles: dict[str, Profile], values: dict[str, float]) -> dict[str, bool]:
    """Whether the profiles let each parameter count as identified at its calibrated ``values``: its own profile, if
    any, has neither end open and a bracket's half-width within the precision needed, and along every profile it was
    refitted in (:data:`.profile.PARTNERS`) its refitted values over the values the frames cannot tell from the best
    stay within that precision: parameters that move along a ridge are pinned no better than it."""
    own = {}
    for name, prof in profiles.items():
        own[name] = not (prof.open_low or prof.open_high) and (prof.bracket[1] - prof.bracket[0]) / 2 <= _allowed(
            name, values[name]
        )

    def follows(prof: Profile, name: str) -> bool:  # ``name`` stays put along the part of ``prof`` not told apart
        inside = (prof.values >= prof.interval[0]) & (prof.values <= prof.interval[1])
        moved = np.ptp(prof.partners[name][inside])
        return moved <= _allowed(name, float(np.median(prof.partners[name][inside])))

    return {
        p.name: own.get(p.name, True)
        and all(follows(prof, p.name) for prof in profiles.values() if p.name in prof.partners)
        for p in P.PARAMETERS
    }


def ridge_ranges(profiles: dict[str, Profile], values: dict[str, float]) -> dict[str, tuple[float, float]]:
    """Each parameter's range over the scenes the single frames leave open: its own profile's bracket (the nearest
    values told apart from the best), its refitted values over the bracket of every profile it was refitted along
    (:data:`.profile.PARTNERS`), and its calibrated ``values`` (which whole windows may have chosen along such a
    ridge). A sigma sees the curvature at one point; this is how far a ridge lets the parameter move, to the
    profiles' spacing. Parameters neither profiled nor refitted along a profile are left out."""
    seen: dict[str, list[float]] = {}
    for name, prof in profiles.items():
        inside = (prof.values >= prof.bracket[0]) & (prof.values <= prof.bracket[1])
        seen.setdefault(name, []).extend(prof.values[inside])
        for partner, refitted in prof.partners.items():
            seen.setdefault(partner, []).extend(refitted[inside])
    return {name: (min(*found, values[name]), max(*found, values[name])) for name, found in seen.items()}


def _allowed(name: str, value: float) -> float:
    """The precision the report needs of parameter ``name`` at ``value`` (file units)."""
    tol, kind = PRECISION[name]
    return tol * abs(value) if kind == "rel" else tol


def document(cal: Calibration, footage: Footage) -> dict[str, Any]:
    """The report's content: JSON-safe, finite numbers; scored against the truth when the recording is synthetic."""
    before, after = cal.guess.as_dict(), cal.scene.as_dict()
    truth = load_truth(footage.path)
    values = {p.name: _value(after, p.name) for p in P.PARAMETERS}
    pinned, ranges = profile_verdicts(cal.profiles, values), ridge_ranges(cal.profiles, values)
    rows = []
    for p in P.PARAMETERS:
        value, sigma = values[p.name], cal.sigma.get(p.name, math.inf)
        tol, kind = PRECISION[p.name]
        prof = cal.profiles.get(p.name)
        held = p.name in cal.held
        identified = math.isfinite(sigma) and sigma <= _allowed(p.name, value) and pinned[p.name]
        rows.append(
            {
                "name": p.name,
                "before": _value(before, p.name),
                "after": value,
                "sigma": sigma if math.isfinite(sigma) else None,
                "identified": None if held else bool(identified),
                "held": held,
                "range": None if p.name not in ranges else [float(v) for v in ranges[p.name]],
                "precision_needed": tol,
                "precision_kind": kind,
                "profile": None if prof is None else prof.as_dict(),
            }
        )
    top = footage.full_scale
    return {
        "schema": SCHEMA,
        "recording": str(footage.path),
        "bit_depth": footage.bit_depth,
        "frames_fitted": [int(i) for i in footage.indices],
        "guess_sha256": cal.guess.sha256,
        "scene_sha256": cal.scene.sha256,
        "parameters": rows,
        "kept_unidentifiable": P.UNIDENTIFIABLE,
        "roi": {
            "before": list(cal.guess.camera.roi),
            "after": list(cal.scene.camera.roi),
            "subpixel": [round(v, 3) for v in cal.roi],
            "correlation": round(cal.roi_score, 4),
        },
        "residual_rms_dn": {"before": cal.residual_before * top, "after": cal.residual_after * top},
        "noise": {
            "full_well_e": cal.noise.full_well_e,
            "read_noise_e": cal.noise.read_noise_e,
            "read_noise_dn": cal.noise.read_noise_fraction * top,
            "static_pixels": cal.noise.pixels,
            "shot_noise_seen": cal.noise.full_well_e > 0,
            "identified": cal.noise.identified,
        },
        "artifacts": {
            "found": cal.spheres_found,
            "guess_spheres": len(cal.guess.spheres),
            "spheres": [dict(zip(("x", "y", "z", "radius"), map(float, s))) for s in cal.scene.spheres]
            if cal.spheres_found
            else None,
            "material": cal.scene.sphere_material.model_dump(),
        },
        "motion": {"columns": ["d", "p", "a", "b"], "frames": [[float(v) for v in m] for m in cal.motion]},
        "starts": cal.starts,
        "descent": cal.moves,
        "ridge": {"windows": [w.as_dict() for w in footage.lab_windows], "points": cal.ridge},
        "systematic": spread(cal.ridge),
        "seconds": cal.seconds,
        "renderer_builds": cal.builds,
        "versus_truth": None if truth is None else score(cal.scene, truth),
        "uncertainty_note": "1 sigma from the final stage's Gauss-Newton covariance with the motion marginalised; "
        "blurred pixels are correlated, so read these as lower bounds. A profiled parameter's 'interval' is the "
        "range of profiled values whose finest-level cost (each frame's motion refitted, and the parameters it trades "
        "with, profile.PARTNERS; the rest of the scene held) the frames cannot tell from the best at 2 standard "
        "errors, its 'bracket' the nearest values told apart either side; 'open' ends may reach further; it counts "
        "as identified only when neither end is open and the bracket's half-width is within the precision needed, "
        "and a parameter refitted along another's profile only when its refitted values stay within that precision "
        "over the other's interval. A parameter's 'range' spans its values over every profile's bracket (its own, and "
        "its refitted values where it trades with the profiled one) and its calibrated value, which whole windows may "
        "have chosen along such a ridge: how far the scenes the single frames leave open let it move. A 'held' "
        "parameter kept the guess's value (calibrate --hold: the user's measurement): not fitted, so neither "
        "identified nor not. 'systematic': per parameter whose ridge the whole windows scored, how far the lab windows' "
        "refined offset and first mode move from the chosen scene's over the points neither the profiles nor the "
        "windows told apart (median over windows, the largest over the points; the offset in mm, the rest relative): "
        "what this calibration leaves open in the numbers a method reads through its scene, one step along each "
        "profile (a lower estimate, not a bound; a parameter held at a measured value has none)",
    }


def figure(cal: Calibration, footage: Footage, path: Path) -> None:
    """Lab frames (top), the calibrated scene rendered with their fitted motion (middle), the difference (bottom),
    for SHOWN frames spread over the phases (sorted by the dominant mode's amplitude a)."""
    plt = pyplot()
    order = np.argsort(cal.motion[:, 2])
    pick = order[np.unique(np.linspace(0, len(order) - 1, min(SHOWN, len(order))).round().astype(int))]
    lab = crop(footage.frames, cal.scene)[pick]
    synthesis = Synthesis()
    synthesis.use(cal.finest)  # the rays the finest level fitted with
    synth = synthesis.stored(cal.scene, cal.motion[pick])
    top = max(float(lab.max()), float(synth.max()), 1e-6)
    fig, axes = plt.subplots(3, len(pick), figsize=(2.2 * len(pick), 6.8), squeeze=False)
    for j, k in enumerate(pick):
        for i, (img, cmap, lim) in enumerate(
            (
                (lab[j], "gray", (0, top)),
                (synth[j], "gray", (0, top)),
                (lab[j] - synth[j], "coolwarm", (-top / 2, top / 2)),
            )
        ):
            ax = axes[i, j]
            ax.imshow(img, cmap=cmap, vmin=lim[0], vmax=lim[1])
            ax.set_xticks([]), ax.set_yticks([])
        a, b = cal.motion[k, 2:]
        axes[0, j].set_title(f"frame {int(footage.indices[k])}\na={a * 1e3:.0f} b={b * 1e3:.0f} um", fontsize=8)
    for i, label in enumerate(("lab", "calibrated render", "lab - render")):
        axes[i, 0].set_ylabel(label)
    fig.suptitle(
        f"{footage.path.name}: residual RMS {cal.residual_before * footage.full_scale:.1f} -> "
        f"{cal.residual_after * footage.full_scale:.1f} DN",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(cal: Calibration, footage: Footage, scene_out: Path) -> tuple[Path, Path]:
    """Write the calibrated scene, its report JSON and PNG; returns the report's two paths."""
    scene_out.write_text(json.dumps(cal.scene.as_dict(), indent=2) + "\n")
    doc_path, png_path = report_paths(scene_out)
    doc_path.write_text(json.dumps(document(cal, footage), indent=1, allow_nan=False) + "\n")
    figure(cal, footage, png_path)
    return doc_path, png_path
