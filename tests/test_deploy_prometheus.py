"""deploy/prometheus: the config and rules pass promtool, every alert is proven to fire (and to stay
quiet) by `promtool test rules`, and the rules read only metrics of the contract (deploy/metrics.txt)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from metric_contract import load_contract, metric_names_in, rule_names_in, series_names

PROMETHEUS = Path(__file__).resolve().parents[1] / "deploy" / "prometheus"
RULE_FILES = sorted((PROMETHEUS / "rules").glob("*.yml"))
#: The alerts the deployment promises (issue 7), each with a test in tests/alerts_test.yml.
ALERTS = {
    "MeniscopeUnsettledEjections",
    "MeniscopeFrequencyDrift",
    "MeniscopeDroppedFrames",
    "MeniscopeSourceDown",
    "MeniscopeNotReady",
    "MeniscopeDown",
    "MeniscopeNoSignal",
    "MeniscopeHistoryFailing",
    "MeniscopeTriggerDisagrees",
}


def _promtool(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("promtool")
    if exe is None:
        pytest.skip("promtool not found (Debian package prometheus)")
    return subprocess.run([exe, *args], cwd=PROMETHEUS, capture_output=True, text=True, timeout=60)


def _rules() -> list[dict]:
    return [
        rule for path in RULE_FILES for group in yaml.safe_load(path.read_text())["groups"] for rule in group["rules"]
    ]


def test_promtool_accepts_the_config_and_its_rule_files() -> None:
    result = _promtool("check", "config", "prometheus.yml")
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"SUCCESS: {len(RULE_FILES)} rule files found" in result.stdout


def test_promtool_accepts_the_rules() -> None:
    result = _promtool("check", "rules", *(str(p.relative_to(PROMETHEUS)) for p in RULE_FILES))
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_alert_fires_in_the_rule_unit_tests() -> None:
    result = _promtool("test", "rules", "tests/alerts_test.yml")
    assert result.returncode == 0, result.stdout + result.stderr
    unit = yaml.safe_load((PROMETHEUS / "tests/alerts_test.yml").read_text())
    groups = [group["name"] for path in RULE_FILES for group in yaml.safe_load(path.read_text())["groups"]]
    assert sorted(unit["group_eval_order"]) == sorted(groups), "an unlisted group is evaluated in random order"
    tests = unit["tests"]
    fired = {case["alertname"] for t in tests for case in t.get("alert_rule_test", []) if case["exp_alerts"]}
    assert fired == ALERTS == {r["alert"] for r in _rules() if "alert" in r}


def test_the_rules_read_only_contract_metrics_and_recorded_series() -> None:
    exported = series_names(load_contract())
    recorded = {r["record"] for r in _rules() if "record" in r}
    for rule in _rules():
        unknown = metric_names_in(rule["expr"]) - exported
        assert not unknown, f"{rule.get('record') or rule.get('alert')} reads {unknown}, not in deploy/metrics.txt"
        missing = rule_names_in(rule["expr"]) - recorded
        assert not missing, f"{rule.get('record') or rule.get('alert')} reads {missing}, recorded nowhere"


def test_every_alert_has_a_severity_and_a_summary() -> None:
    for rule in _rules():
        if "alert" in rule:
            assert rule["labels"]["severity"] in {"warning", "critical"} and rule["annotations"]["summary"], rule[
                "alert"
            ]
