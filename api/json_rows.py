"""JSON lists of many rows in a pydantic response model's shape, encoded by msgspec.

A busy window is thousands of rows: a pydantic model per row and FastAPI's validation of
the list again cost ~30 µs a row. The routers keep their pydantic model (it documents the
answer in OpenAPI) and encode with a msgspec struct derived from it, so the field list is
written once.
"""

from __future__ import annotations

from typing import Any

import msgspec
from fastapi import Response
from pydantic import BaseModel


class JsonRows:
    """`struct(*values)` builds one row (the model's fields, in order); `response(rows)`
    is the JSON of them (a list of rows, or one: a row may hold another model's rows)."""

    def __init__(self, model: type[BaseModel]) -> None:
        self.struct = msgspec.defstruct(
            f"{model.__name__}Json",
            [(name, field.annotation) for name, field in model.model_fields.items()],
        )
        self._encode = msgspec.json.Encoder().encode

    def response(self, rows: Any) -> Response:
        return Response(self._encode(rows), media_type="application/json")
