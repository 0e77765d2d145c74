"""The supervisor (service.pipeline.supervisor) keeps the pipeline running: what its health says about which run."""

from __future__ import annotations

from pathlib import Path

from service.errors import MeniscopeError
from service.pipeline.supervisor import Supervisor
from service.server.settings import ServiceSettings
from tests.servicekit import wait_for


class FailsAsTheSourceChanges(Supervisor):
    """A supervisor whose first run fails just after the source was changed (PUT /api/v1/config landing while
    the run fails; its wake-up is left out, so the retry waits its second and its health can be read); later
    runs last until stopped. ``runs``: the source of each run, in order."""

    def __init__(self, first: ServiceSettings, second: ServiceSettings) -> None:
        super().__init__(first, sink=None)  # type: ignore[arg-type]  # no pipeline runs: the runs are these
        self.second, self.runs = second, []

    def _run_once(self, settings: ServiceSettings) -> bool:
        self.runs.append(settings.source)
        if len(self.runs) == 1:
            self.settings = self.second
            raise MeniscopeError(settings.source, "the camera went away")
        self._run_stop.wait()
        return False


def test_a_failed_run_is_reported_with_its_own_source_though_the_source_changed_meanwhile(tmp_path: Path) -> None:
    first = ServiceSettings(source="zmq+tcp://127.0.0.1:5001", data_dir=tmp_path)
    second = ServiceSettings(source="zmq+tcp://127.0.0.1:5002", data_dir=tmp_path)
    supervisor = FailsAsTheSourceChanges(first, second).start()
    try:
        health = wait_for(lambda: (h := supervisor.health()).state == "retrying" and h, 10, "the retry", interval=0.005)
        assert health.reason.startswith("zmq+tcp://127.0.0.1:5001: the camera went away (attempt 1;")
        assert health.source == {"uri": "zmq+tcp://127.0.0.1:5001"}
        supervisor.reconfigure(second)
        wait_for(lambda: len(supervisor.runs) == 2, 10, "the run with the new source")
        assert supervisor.runs == [first.source, second.source]
        assert supervisor.health().source == {"uri": "zmq+tcp://127.0.0.1:5002"}
    finally:
        supervisor.stop()
