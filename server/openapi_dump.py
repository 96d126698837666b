"""Print the service's OpenAPI document: ``python -m hktex_server.openapi_dump > openapi/openapi.json``.

The checked-in ``openapi/openapi.json`` is what outside tools read (code generators, the
schemathesis tests); ``tests/test_openapi.py`` regenerates it with :func:`openapi_document`
and fails when the two differ, so the file can never silently drift from the code.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO_FILE = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def openapi_document() -> dict[str, Any]:
    """The app's OpenAPI document; building the app touches nothing (no lifespan runs)."""
    from hktex_server.app import create_app
    from hktex_server.settings import Settings

    with tempfile.TemporaryDirectory(prefix="hktex-openapi-") as tmp:
        app = create_app(Settings(data_dir=Path(tmp), workers=0, tokens=""))
        return app.openapi()


def render(document: dict[str, Any]) -> str:
    """Stable text (sorted keys, 2-space indent, final newline) so diffs are reviewable."""
    return json.dumps(document, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    text = render(openapi_document())
    if args and args[0] in ("-w", "--write"):
        REPO_FILE.parent.mkdir(parents=True, exist_ok=True)
        REPO_FILE.write_text(text)
        print(f"wrote {REPO_FILE}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
