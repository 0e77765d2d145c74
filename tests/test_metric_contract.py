"""tests/metric_contract.py: the contract file parses, and `missing_from` (which the service's /metrics test
can call) accepts a complete exposition and names what an incomplete one lacks."""

from __future__ import annotations

import shutil
import subprocess

import pytest
from metric_contract import load_contract, missing_from
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

KINDS = {"counter": Counter, "gauge": Gauge, "histogram": Histogram}


def _exposition(skip: str = "", kind_of: dict[str, str] | None = None, label_values: int | None = None) -> str:
    """/metrics text of a fresh registry holding the contract, less ``skip``, with types and labels as asked."""
    registry = CollectorRegistry()
    for m in load_contract().values():
        if m.name == skip:
            continue
        kind = (kind_of or {}).get(m.name, m.kind)
        name = m.name.removesuffix("_total") if kind == "counter" else m.name
        metric = KINDS[kind](name, m.name, list(m.labels), registry=registry)
        for label, values in m.labels.items():
            for value in values[:label_values]:
                metric.labels(**{label: value})
    return generate_latest(registry).decode()


def test_the_contract_names_the_issue_metrics() -> None:
    contract = load_contract()
    assert len(contract) == 23 and {m.kind for m in contract.values()} == {"counter", "gauge", "histogram"}
    assert contract["meniscope_windows_total"].labels == {"status": ("ok", "settled", "unresolved", "failed")}
    assert all(m.name.endswith("_total") == (m.kind == "counter") for m in contract.values())


def test_a_complete_exposition_passes() -> None:
    assert missing_from(_exposition()) == []


def test_the_contract_names_pass_promtool_lint() -> None:
    """Base units, _total counters, help text: what `promtool check metrics` asks of an exporter."""
    if shutil.which("promtool") is None:
        pytest.skip("promtool not found (Debian package prometheus)")
    result = subprocess.run(
        ["promtool", "check", "metrics"], input=_exposition(), capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and not result.stdout.strip(), result.stdout + result.stderr


@pytest.mark.parametrize(
    "args, problem",
    [
        ({"skip": "meniscope_source_up"}, "meniscope_source_up: not exported"),
        (
            {"kind_of": {"meniscope_settling_time_seconds": "gauge"}},
            "meniscope_settling_time_seconds: a gauge, not a histogram",
        ),
        ({"label_values": 2}, "meniscope_windows_total: no series with status='unresolved'"),
    ],
)
def test_an_incomplete_exposition_is_named(args: dict, problem: str) -> None:
    assert problem in missing_from(_exposition(**args))
