"""deploy/grafana: the dashboard is well formed, reads only the metric contract (deploy/metrics.txt) and
recorded series, shows every contract metric somewhere, and names the provisioned datasource."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from metric_contract import load_contract, metric_names_in, rule_names_in, series_names

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
GRAFANA = DEPLOY / "grafana"
DASHBOARD = GRAFANA / "dashboards" / "meniscope.json"


@pytest.fixture(scope="module")
def dashboard() -> dict[str, Any]:
    return json.loads(DASHBOARD.read_text())


@pytest.fixture(scope="module")
def recorded() -> dict[str, str]:
    """Recording rules: name -> expression."""
    return {
        r["record"]: r["expr"]
        for path in sorted((DEPLOY / "prometheus" / "rules").glob("*.yml"))
        for g in yaml.safe_load(path.read_text())["groups"]
        for r in g["rules"]
        if "record" in r
    }


def _panels(dashboard: dict[str, Any]) -> Iterator[dict[str, Any]]:
    for panel in dashboard["panels"]:
        yield panel
        yield from panel.get("panels", [])  # collapsed rows hold theirs


def _exprs(dashboard: dict[str, Any]) -> Iterator[tuple[str, str]]:
    """(where, PromQL) of every query: panel targets, template variables, annotations."""
    for panel in _panels(dashboard):
        for target in panel.get("targets", []):
            yield panel["title"], target["expr"]
    for var in dashboard["templating"]["list"]:
        yield f"variable {var['name']}", var["query"]["query"]
    for annotation in dashboard["annotations"]["list"]:
        yield f"annotation {annotation['name']}", annotation["expr"]


def test_the_dashboard_is_well_formed(dashboard: dict[str, Any]) -> None:
    assert dashboard["uid"] and dashboard["title"] and dashboard["schemaVersion"] >= 36
    panels = list(_panels(dashboard))
    assert len({p["id"] for p in panels}) == len(panels), "panel ids repeat"
    for p in panels:
        grid = p["gridPos"]
        assert grid["x"] >= 0 and grid["w"] >= 1 and grid["x"] + grid["w"] <= 24 and grid["h"] >= 1, p["title"]
        if p["type"] != "row":
            assert p["targets"] and len({t["refId"] for t in p["targets"]}) == len(p["targets"]), p["title"]


def test_panels_do_not_overlap(dashboard: dict[str, Any]) -> None:
    cells: dict[tuple[int, int], str] = {}
    for p in _panels(dashboard):
        g = p["gridPos"]
        for x in range(g["x"], g["x"] + g["w"]):
            for y in range(g["y"], g["y"] + g["h"]):
                assert (x, y) not in cells, f"{p['title']!r} overlaps {cells[(x, y)]!r}"
                cells[(x, y)] = p["title"]


def test_queries_read_only_contract_metrics_and_recorded_series(
    dashboard: dict[str, Any], recorded: dict[str, str]
) -> None:
    exported = series_names(load_contract())
    for where, expr in _exprs(dashboard):
        assert not metric_names_in(expr) - exported, (
            f"{where}: {metric_names_in(expr) - exported} not in deploy/metrics.txt"
        )
        assert not rule_names_in(expr) - set(recorded), (
            f"{where}: {rule_names_in(expr) - set(recorded)} recorded nowhere"
        )


def test_every_contract_metric_is_on_the_dashboard(dashboard: dict[str, Any], recorded: dict[str, str]) -> None:
    """Read directly or through a recording rule the dashboard shows."""
    shown: set[str] = set()
    for _, expr in _exprs(dashboard):
        shown |= metric_names_in(expr)
        for rule in rule_names_in(expr):
            shown |= metric_names_in(recorded[rule])
    unseen = [m.name for m in load_contract().values() if not set(m.series()) & shown]
    assert not unseen, f"not on the dashboard: {unseen}"


def test_the_dashboard_uses_the_provisioned_datasource(dashboard: dict[str, Any]) -> None:
    sources = yaml.safe_load((GRAFANA / "provisioning/datasources/prometheus.yml").read_text())["datasources"]
    [prometheus] = [s for s in sources if s["type"] == "prometheus"]
    assert prometheus["url"] == "http://prometheus:9090"
    refs = [p["datasource"] for p in _panels(dashboard) if p["type"] != "row"]
    refs += [t["datasource"] for p in _panels(dashboard) for t in p.get("targets", [])]
    refs += [v["datasource"] for v in dashboard["templating"]["list"]]
    refs += [a["datasource"] for a in dashboard["annotations"]["list"]]
    assert refs and all(r == {"type": "prometheus", "uid": prometheus["uid"]} for r in refs)


def test_the_provider_loads_the_folder_compose_mounts() -> None:
    [provider] = yaml.safe_load((GRAFANA / "provisioning/dashboards/meniscope.yml").read_text())["providers"]
    compose = yaml.safe_load((DEPLOY.parent / "docker-compose.yml").read_text())
    mounts = dict(v.split(":")[:2][::-1] for v in compose["services"]["grafana"]["volumes"])
    assert mounts[provider["options"]["path"]] == "./deploy/grafana/dashboards"
    assert mounts["/etc/grafana/provisioning"] == "./deploy/grafana/provisioning"
