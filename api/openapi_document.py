"""The API's OpenAPI document, as this code defines it, printed as JSON.

The replay UI's API types (replay-ui/src/lib/api-schema.d.ts) are generated from it by
openapi-typescript: `make api-types` regenerates them, and tests/api/test_ui_api_types.py
fails when they no longer match the routes. The document is built from the settings'
defaults, not from the environment, so the same code always gives the same document.
"""

from __future__ import annotations

import json
import sys
from typing import Any

from mapservice.api.app import create_app
from mapservice.api.context import context_of
from mapservice.settings import Settings


def openapi_document() -> dict[str, Any]:
    """The document `/openapi.json` serves, for the default settings (no store is needed:
    building it reads only the routes)."""
    app = create_app(Settings.model_construct(), None)
    try:
        return app.openapi()
    finally:
        context_of(app).export_executor.shutdown(wait=False)


def main() -> None:
    json.dump(openapi_document(), sys.stdout, indent=2, sort_keys=True)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
