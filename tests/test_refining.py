"""The refinement lane's parts (service/pipeline/refining.py): the newest-window slot, the frames kept for it, and
the history that takes its updates under the window's own id."""

from __future__ import annotations

import json

import numpy as np


def test_the_search_starts_on_every_demo_window(demo_cine) -> None:  # type: ignore[no-untyped-def]
    """``analyze --refine``'s start (one-mode fits of each coefficient's series) on each window of the demo: window 0's
    fit of one series was polished into an unresolved fit that gave no reason, which raised (analyze --refine of the
    demo failed); an unresolved fit says why."""
    from service import DEFAULT_MODELS, DEFAULT_SCENE
    from service.analysis.fit import fit_window
    from service.analysis.results import FitSettings
    from service.inverse import synthesis
    from service.inverse.network import NetworkMethod
    from service.pipeline.demo import DEMO_TRUTH
    from service.recordings import open_recording
    from service.recordings.roi import roi_frames
    from service.scene import Scene

    truth, scene = json.loads(DEMO_TRUTH.read_text()), Scene.load(DEFAULT_SCENE)
    with open_recording(demo_cine) as rec:
        coefficients = NetworkMethod(DEFAULT_MODELS, scene).infer(roi_frames(rec, scene, 0, len(rec))).coefficients
    fps = truth["recording"]["fps"]
    skip = FitSettings().transient_frames(fps)
    for w in truth["windows"]:
        lo, end = w["start_frame"] + skip, w["end_frame"]
        t = (np.arange(lo, end) - w["start_frame"]) / fps
        assert synthesis.start_motion(coefficients[lo:end], t, fps).f1 > 0
        for column in coefficients[lo:end].T:
            result = fit_window(column, fps, FitSettings(max_modes=1))
            assert result.status == "ok" or result.reason
