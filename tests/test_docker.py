"""Static checks of docker/ (Docker itself cannot run here, see docs/deployment.md).

The containers' commands are `hktex ...` invocations: parse each with the real CLI parser, so
a renamed flag breaks this test rather than a deployment.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from hktex_engine.cli import build_parser

DOCKER = Path(__file__).resolve().parents[1] / "docker"


def _compose() -> dict:
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load((DOCKER / "docker-compose.yml").read_text())


def _parse_hktex(argv: list[str]):
    assert argv[0] == "hktex", argv
    return build_parser().parse_args(argv[1:])


def test_compose_commands_are_valid_hktex_invocations() -> None:
    services = _compose()["services"]
    assert {"db", "api", "worker"} <= set(services)
    for name in ("api", "worker", "worker-gpu"):
        command = re.sub(r"\$\{[^}]+\}", "x", services[name]["command"])  # compose variables
        args = _parse_hktex(shlex.split(command))
        assert args.command == ("serve" if name == "api" else "worker")
        assert args.database.startswith("postgresql+psycopg://")
        assert str(args.data_dir) == "/data"
    assert services["api"]["command"].split().count("0.0.0.0") == 1
    assert "HKTEX_TOKENS" in services["api"]["environment"]  # non-loopback bind needs tokens
    for name in ("worker", "worker-gpu"):  # job processes inherit the environment
        assert "HKTEX_TOKENS" not in services[name]["environment"]


def test_every_service_shares_the_data_volume() -> None:
    services = _compose()["services"]
    for name in ("api", "worker", "worker-gpu"):
        assert "hktex-data:/data" in services[name]["volumes"]


@pytest.mark.parametrize("name", ["Dockerfile.cpu", "Dockerfile.cuda"])
def test_dockerfile_pins_torch_and_runs_a_valid_command(name: str) -> None:
    text = (DOCKER / name).read_text()
    import tomllib

    project = tomllib.loads((DOCKER.parent / "pyproject.toml").read_text())["project"]
    pinned = next(d for d in project["dependencies"] if d.startswith("torch=="))
    version = pinned.removeprefix("torch==")
    assert f'"{pinned}"' in text or f"ARG TORCH_VERSION={version}" in text, pinned
    assert "download.pytorch.org/whl/" in text
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", text, re.M).group(1))
    args = _parse_hktex(cmd)
    assert args.command in ("serve", "worker")
