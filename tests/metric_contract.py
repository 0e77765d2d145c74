"""The metric names of deploy/metrics.txt, parsed once for every test that checks rules, panels or /metrics."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

CONTRACT = Path(__file__).resolve().parents[1] / "deploy" / "metrics.txt"
#: Series a histogram named h exports besides h itself.
HISTOGRAM_SUFFIXES = ("_bucket", "_sum", "_count")


@dataclass(frozen=True)
class Metric:
    """One line of the contract: name, type (counter, gauge, histogram) and allowed label values."""

    name: str
    kind: str
    labels: dict[str, tuple[str, ...]]

    def series(self) -> tuple[str, ...]:
        """The sample names it exports: the histogram's three series, or the name alone."""
        return tuple(self.name + s for s in HISTOGRAM_SUFFIXES) if self.kind == "histogram" else (self.name,)


def load_contract(path: Path = CONTRACT) -> dict[str, Metric]:
    """Metrics by name, in file order."""
    metrics: dict[str, Metric] = {}
    for line in path.read_text().splitlines():
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        name, kind, *labels = fields
        metrics[name] = Metric(name, kind, {k: tuple(v.split("|")) for k, v in (x.split("=", 1) for x in labels)})
    return metrics


def series_names(contract: dict[str, Metric]) -> set[str]:
    """Every sample name the service exports."""
    return {s for m in contract.values() for s in m.series()}


def metric_names_in(expr: str) -> set[str]:
    """The meniscope_* metric names a PromQL expression reads (recording-rule names, with colons, excluded)."""
    return set(re.findall(r"(?<![\w:])meniscope_[a-z0-9_]+(?![\w:])", expr))


def rule_names_in(expr: str) -> set[str]:
    """The recording rules (level:metric:operations, the only names with colons) a PromQL expression reads."""
    return set(re.findall(r"(?<![\w:\"])[a-zA-Z_]\w*(?::\w+)+", expr))


def missing_from(exposition: str, contract: dict[str, Metric] | None = None) -> list[str]:
    """What a /metrics text lacks of the contract: absent metrics, wrong types, label values not exported.

    Label values must be there from the start (children created at 0), so rates see their first increment.
    """
    from prometheus_client.parser import text_string_to_metric_families

    contract = load_contract() if contract is None else contract
    families = {f.name: f for f in text_string_to_metric_families(exposition)}
    problems = []
    for m in contract.values():
        family = families.get(m.name.removesuffix("_total") if m.kind == "counter" else m.name)
        if family is None:
            problems.append(f"{m.name}: not exported")
        elif family.type != m.kind:
            problems.append(f"{m.name}: a {family.type}, not a {m.kind}")
        else:
            for label, values in m.labels.items():
                seen = {s.labels.get(label) for s in family.samples}
                problems += [f"{m.name}: no series with {label}={v!r}" for v in values if v not in seen]
    return problems
