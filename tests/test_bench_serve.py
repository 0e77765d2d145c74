"""`meniscope bench serve --variants`: the service settings compared side by side, as the settings parse them."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from service.bench.serve import parse_variants, register
from service.errors import MeniscopeError


def test_variants_are_groups_of_settings_and_an_empty_group_is_the_defaults() -> None:
    assert parse_variants("") == [("", {})]
    assert parse_variants("batch_ms=1000, read_frames=128;;batch_ms=2") == [
        ("batch_ms=1000,read_frames=128", {"batch_ms": "1000", "read_frames": "128"}),
        ("", {}),
        ("batch_ms=2", {"batch_ms": "2"}),
    ]


def test_a_variant_that_is_not_key_value_pairs_is_one_error_naming_the_option() -> None:
    with pytest.raises(MeniscopeError, match="--variants.*KEY=VALUE"):
        parse_variants("batch_ms=2;fast")


def test_a_variant_the_settings_refuse_is_one_error_naming_it_before_anything_runs(
    demo_cine: Path, tmp_path: Path
) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["serve", "--source", str(demo_cine), "--out", str(tmp_path), "--variants", "batch_ms=-1"])
    with pytest.raises(MeniscopeError, match="--variants.*'batch_ms=-1'"):
        args.func(args)
