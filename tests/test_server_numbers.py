"""Every number a client can send is range-checked into a 4xx (issue 11: a face id past 64
bits was a 500 ``OverflowError``).

The numeric fields are found by walking the checked-in OpenAPI document (so a new route or
field is covered without editing this file): every integer/number query parameter and every
integer/number leaf of every JSON request body, nested objects and array items included.

1. Each must declare both bounds (an unbounded number is a promise the engine cannot keep).
2. Hypothesis sends values outside those bounds (just past them, and far past: 2**64, 10**20,
   +-1e308) to a real service on loopback; every answer must be a 422 with a reason.
"""

from __future__ import annotations

import json
from typing import Any

import httpx
import pytest
from hktex_server.openapi_dump import REPO_FILE
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.server_support import LiveServer, fast_settings

DOC = json.loads(REPO_FILE.read_text())
HUGE_INTS = [2**63, 2**64, 10**20, -(2**63) - 1, -(2**64), -(10**20)]
HUGE_FLOATS = [1e308, -1e308, 1e300, -1e300]


def _resolve(schema: dict) -> dict:
    """Follow ``$ref`` and drop the ``null`` branch of ``anyOf`` (optional fields)."""
    while True:
        if "$ref" in schema:
            name = schema["$ref"].rsplit("/", 1)[1]
            schema = DOC["components"]["schemas"][name]
            continue
        branches = [b for b in schema.get("anyOf", []) if b.get("type") != "null"]
        if len(branches) == 1:
            schema = branches[0]
            continue
        return schema


def _numeric_leaves(schema: dict, path: tuple = ()) -> list[tuple[tuple, dict]]:
    schema = _resolve(schema)
    kind = schema.get("type")
    if kind in ("integer", "number"):
        return [(path, schema)]
    if kind == "array":
        return _numeric_leaves(schema.get("items", {}), (*path, 0))
    leaves = []
    for name, sub in schema.get("properties", {}).items():
        leaves += _numeric_leaves(sub, (*path, name))
    return leaves


def _cases() -> list[tuple[str, str, str, tuple, dict]]:
    """(method, path, where, field path, schema) for every numeric input of the API."""
    out = []
    for route, ops in DOC["paths"].items():
        for method, op in ops.items():
            for param in op.get("parameters", []):
                schema = _resolve(param.get("schema", {}))
                if param["in"] == "query" and schema.get("type") in ("integer", "number"):
                    out.append((method, route, "query", (param["name"],), schema))
            body = op.get("requestBody", {}).get("content", {}).get("application/json")
            if body:
                for path, schema in _numeric_leaves(body["schema"]):
                    out.append((method, route, "body", path, schema))
    return out


CASES = _cases()


def _bounds(schema: dict) -> tuple[float | None, float | None]:
    if schema.get("enum"):  # a closed set of numbers (e.g. bake resolutions) is bounded
        return min(schema["enum"]), max(schema["enum"])
    lo = schema.get("minimum", schema.get("exclusiveMinimum"))
    hi = schema.get("maximum", schema.get("exclusiveMaximum"))
    return lo, hi


def test_the_walk_finds_the_known_numbers() -> None:
    found = {(r, ".".join(map(str, p))) for _m, r, _w, p, _s in CASES}
    for expected in [
        ("/v1/jobs", "priority"),
        ("/v1/jobs", "params.seed"),
        ("/v1/jobs", "spectra.anisotropies.0"),
        ("/v1/kernelsets/{kernelset_id}/albedo", "face_ids.0"),
        ("/v1/kernelsets/{kernelset_id}/albedo", "barycentrics.0.0"),
        ("/v1/kernelsets/{kernelset_id}/render", "spp"),
        ("/v1/jobs", "limit"),
    ]:
        assert expected in found, expected


@pytest.mark.parametrize(
    ("method", "route", "where", "path", "schema"),
    CASES,
    ids=[f"{m} {r} {'.'.join(map(str, p))}" for m, r, _w, p, _s in CASES],
)
def test_every_number_declares_both_bounds(method, route, where, path, schema) -> None:
    lo, hi = _bounds(schema)
    assert lo is not None and hi is not None, f"{method} {route} {where} {path}: unbounded"


def _out_of_range(schema: dict) -> st.SearchStrategy:
    lo, hi = _bounds(schema)
    integer = schema["type"] == "integer"
    parts: list[st.SearchStrategy] = [st.sampled_from(HUGE_INTS)]
    if not integer:
        parts.append(st.sampled_from(HUGE_FLOATS))
    if lo is not None:
        below = (
            lo if "exclusiveMinimum" in schema else lo - (1 if integer else 1e-6 * max(1, abs(lo)))
        )
        parts.append(
            st.integers(max_value=int(below) if integer else int(lo) - 1)
            if integer
            else st.floats(max_value=below, allow_nan=False, allow_infinity=False)
        )
    if hi is not None:
        above = (
            hi if "exclusiveMaximum" in schema else hi + (1 if integer else 1e-6 * max(1, abs(hi)))
        )
        parts.append(
            st.integers(min_value=int(above))
            if integer
            else st.floats(min_value=above, allow_nan=False, allow_infinity=False)
        )
    return st.one_of(parts)


def _body(route: str, path: tuple, value: Any) -> dict:
    """A body valid but for ``value`` at ``path`` (arrays get the value as their element 0)."""
    if route.endswith("/albedo"):
        base: dict = (
            {"points": [[0.0, 0.0, 0.0]]}
            if path[0] == "points"
            else {"face_ids": [0], "barycentrics": [[1.0, 0.0, 0.0]]}
        )
    elif route == "/v1/jobs":
        base = {"mesh_id": "msh_nope", "params": {}, "spectra": {}}
    else:
        base = {}
    node: Any = base
    for key, nxt in zip(path[:-1], path[1:], strict=False):
        if isinstance(key, int):
            node = node[key]
            continue
        if key not in node:
            node[key] = [] if isinstance(nxt, int) else {}
        node = node[key]
    last = path[-1]
    if isinstance(last, int):
        if node:
            node[last] = value
        else:
            node.append(value)
    else:
        node[last] = value
    return base


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("numbers")
    st_ = fast_settings(tmp, f"sqlite:///{tmp / 'hktex.db'}", workers=0, compute_workers=1)
    with LiveServer(st_) as server, httpx.Client(base_url=server.url, timeout=30) as client:
        yield client


@pytest.mark.parametrize(
    ("method", "route", "where", "path", "schema"),
    CASES,
    ids=[f"{m} {r} {'.'.join(map(str, p))}" for m, r, _w, p, _s in CASES],
)
def test_out_of_range_numbers_are_422(live, method, route, where, path, schema) -> None:
    url = route.replace("{", "").replace("}", "_nope")  # ids are checked after the numbers

    @settings(
        max_examples=12,
        deadline=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(value=_out_of_range(schema))
    def check(value) -> None:
        if where == "query":
            r = live.request(method, url, params={path[0]: str(value)})
        else:
            r = live.request(method, url, json=_body(route, path, value))
        assert r.status_code == 422, (method, route, path, value, r.status_code, r.text[:300])
        assert r.json()["detail"], r.text

    check()
