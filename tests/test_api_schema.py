"""Every operation of the OpenAPI schema, driven by schemathesis against a running demo service: valid and
invalid requests (seeded, a bounded number per operation), each answer checked against the schema (status
documented, body and content type as declared, no server error, invalid input refused)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from tests.servicekit import request, running_service, service_settings, wait_for

TOKEN = "s3cret"
#: A schema-valid source may still name nothing that opens (a file that is not there, a scheme no adapter
#: has): PUT /api/v1/config refuses it with 422, which the schema documents, so that check accepts 422 there.
CONFIG = schemathesis.config.SchemathesisConfig.from_str("""
[[operations]]
include-path = "/api/v1/config"
include-method = "PUT"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "403", "404", "422"]
""")


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory, demo_cine: Path) -> Iterator[schemathesis.BaseSchema]:
    settings_ = service_settings(
        tmp_path_factory.mktemp("schema"), demo_cine.parent, f"file://{demo_cine}?speed=0.25&loop=1", token=TOKEN
    )
    with running_service(settings_) as base:
        wait_for(lambda: request("GET", base + "/api/v1/windows?limit=1").json()["windows"], 120, "a window")
        yield schemathesis.openapi.from_url(base + "/openapi.json", config=CONFIG)


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(
    max_examples=25,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.function_scoped_fixture],
)
def test_every_operation_answers_as_its_schema_says(case: schemathesis.Case) -> None:
    case.call_and_validate(headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60)
