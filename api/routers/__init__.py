"""One FastAPI router per resource; each route has a stable operation id (tests/api pins them)."""
