"""The bounded JSON reader: depth, size and integer limits hold on hostile text, and valid JSON reads as json does."""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

import pytest

from panogs_core.bounded_json import (
    JsonLimitError,
    JsonLimits,
    JsonSyntaxError,
    loads,
    nesting_depth,
    read_json_file,
)
from panogs_core.errors import InputError


def _depth(value: Any) -> int:  # the reference: levels of nested containers, by recursion over the parsed value
    if isinstance(value, dict):
        return 1 + max((_depth(v) for v in value.values()), default=0)
    if isinstance(value, list):
        return 1 + max((_depth(v) for v in value), default=0)
    return 0


def _random_value(rng: random.Random, depth: int) -> Any:
    kind = rng.choice(["list", "dict", "str", "int", "float"] if depth < 6 else ["str", "int", "float"])
    if kind == "list":
        return [_random_value(rng, depth + 1) for _ in range(rng.randint(0, 3))]
    if kind == "dict":
        return {rng.choice(['a"[', "b\\{", "]}", "k", "é"]) + str(i): _random_value(rng, depth + 1) for i in range(3)}
    if kind == "str":
        return "".join(rng.choice('[]{}"\\,:x\n') for _ in range(rng.randint(0, 6)))
    return rng.randint(-(10**12), 10**12) if kind == "int" else rng.uniform(-1e6, 1e6)


def test_depth_matches_the_parsed_value_on_random_documents() -> None:
    rng = random.Random(0)
    for _ in range(300):
        value = _random_value(rng, 0)
        text = json.dumps(value, ensure_ascii=rng.random() < 0.5)
        assert nesting_depth(text) == _depth(value), text
        assert loads(text) == value


@pytest.mark.parametrize(
    ("text", "depth"),
    [("1", 0), ("[]", 1), ('{"a": [1, {"b": []}]}', 4), ('["[[[[", "\\"[["]', 1), ('{"k]}": {"x{": "]]"}}', 2)],
)
def test_brackets_inside_strings_do_not_count(text: str, depth: int) -> None:
    assert nesting_depth(text) == depth


@pytest.mark.parametrize("levels", [65, 1_000, 200_000])
def test_too_deep_is_refused_with_the_path_and_no_recursion_error(levels: int) -> None:
    text = '{"frames": [{"pose": ' + "[" * levels + "]" * levels + "}]}"
    with pytest.raises(JsonLimitError) as info:
        loads(text, source="scene.json")
    message = str(info.value)
    assert message.startswith("scene.json: nested deeper than the JSON depth limit of 64 levels at frames[0].pose")
    assert "line 1, column" in message
    assert info.value.limit == "depth"
    assert info.value.value == 64


def test_depth_limit_is_exact() -> None:
    limits = JsonLimits(max_depth=3)
    assert loads("[[[1]]]", limits) == [[[1]]]
    with pytest.raises(JsonLimitError):
        loads("[[[[1]]]]", limits)


def test_unclosed_brackets_count_towards_the_depth() -> None:
    # Not JSON, but json.loads would recurse through every "[" before it finds that out.
    with pytest.raises(JsonLimitError):
        loads("[" * 100_000)
    with pytest.raises(JsonSyntaxError):
        loads("[" * 10)


def test_huge_integer_is_refused_before_int_sees_it() -> None:
    text = '{"camera": {"width": ' + "9" * 5000 + "}}"
    with pytest.raises(JsonLimitError) as info:
        loads(text, source="scene.json")
    assert str(info.value) == (
        "scene.json: an integer of 5,000 digits at camera.width (line 1, column 22), "
        "over the JSON integer limit of 20 digits"
    )


def test_integer_limit_counts_digits_not_the_sign_and_leaves_floats_alone() -> None:
    assert loads(str(-(2**63))) == -(2**63)
    assert loads("18446744073709551615") == 2**64 - 1  # 20 digits
    assert loads("0." + "1" * 400) == pytest.approx(1 / 9)  # a long fraction is a float, not an integer
    assert loads('"' + "9" * 100 + '"') == "9" * 100  # digits in a string are text
    with pytest.raises(JsonLimitError):
        loads("[1, -123456789012345678901]")


def test_size_limit() -> None:
    with pytest.raises(JsonLimitError, match="over the JSON size limit of 10 bytes"):
        loads('["' + "x" * 20 + '"]', JsonLimits(max_bytes=10))


def test_not_json() -> None:
    with pytest.raises(JsonSyntaxError, match=r"scene\.json: not valid JSON \(Expecting"):
        loads("{nope", source="scene.json")
    with pytest.raises(JsonSyntaxError, match="not UTF-8"):
        loads(b"\xff\xfe\x00", source="x")
    assert isinstance(JsonSyntaxError("x"), InputError)


def test_bytes_are_read_as_json_loads_reads_them() -> None:
    assert loads('{"a": "é"}'.encode("utf-16")) == {"a": "é"}


def test_file_over_the_size_limit_is_refused_by_its_size(tmp_path: Path) -> None:
    path = tmp_path / "scene.json"
    path.write_bytes(b"[" + b" " * 5_000_000 + b"]")
    with pytest.raises(JsonLimitError, match=r"scene\.json: 5,000,002 bytes, over the JSON size limit of 1,024"):
        read_json_file(path, JsonLimits(max_bytes=1024), name="scene.json")
    path.write_text('{"a": 1}')
    assert read_json_file(path) == {"a": 1}
    with pytest.raises(InputError, match=r"missing\.json: cannot be read"):
        read_json_file(tmp_path / "missing.json")
