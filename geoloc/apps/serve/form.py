"""The settings of `POST /localize`, as the request sends them: form fields or query parameters, each once.

QueryForm is the Pydantic model FastAPI reads both from (the text as sent; the descriptions are query.py's, and
/openapi.json shows them); `sent_settings` joins the two, and the localizer's `parse` parses them, once, into the
QuerySettings everything below the door trusts.
"""

from __future__ import annotations

from collections import Counter

from fastapi import HTTPException, Request
from pydantic import BaseModel, Field

from geoloc.apps.query import ABSTAIN, FOV, HEADING, HEADING_PRIOR, REFINE, TOPK


class QueryForm(BaseModel):
    """One query's settings as text, each left out (None) or sent once; the keys are QuerySettings'."""

    fov: str | None = Field(None, description=FOV)
    topk: str | None = Field(None, description=TOPK)
    heading: str | None = Field(None, description=HEADING)
    heading_prior: str | None = Field(None, description=HEADING_PRIOR)
    abstain: str | None = Field(None, description=ABSTAIN)
    refine: str | None = Field(None, description=REFINE)


FIELDS = tuple(QueryForm.model_fields)
HINTS = {key: field.description for key, field in QueryForm.model_fields.items()}


def sent_settings(form: QueryForm, params: QueryForm) -> tuple[dict, dict]:
    """({key: the text sent}, {key: "form field" or "query parameter", where it came from}); a key sent both ways
    is a 422 naming it."""
    sent, where = {}, {}
    for key in FIELDS:
        in_form, in_params = getattr(form, key), getattr(params, key)
        if in_form is not None and in_params is not None:
            raise HTTPException(422, f"{key} is given both as a form field and as a query parameter: give it once")
        sent[key] = in_params if in_form is None else in_form
        where[key] = "query parameter" if in_form is None and in_params is not None else "form field"
    return sent, where


def each_field_once(endpoint: str, files: dict[str, str], repeated: tuple[str, ...] = ()):
    """The FastAPI dependency of `endpoint`, whose file fields are `files` ({name: what to send}): a form field or
    query parameter it does not take, or one given twice (except the file fields in `repeated`, one per item), is a
    422 naming it, since a form parser keeps only the last of repeated values and the answer would silently use one
    of them."""
    hints = {**files, **HINTS}
    named = f"the file field{'s' if len(files) > 1 else ''} {' and '.join(files)}"

    async def check(request: Request) -> None:
        form = await request.form()  # FastAPI has parsed it for the endpoint's fields: this is that copy
        for where, items, takes in (("form field", form.multi_items(), hints),
                                    ("query parameter", request.query_params.multi_items(), FIELDS)):
            for key, count in Counter(key for key, _ in items).items():
                if key not in takes:
                    raise HTTPException(422, f"unknown {where} {key!r}: {endpoint} takes {named} and "
                                             f"{', '.join(FIELDS)} (form fields or query parameters)")
                if count > 1 and key not in repeated:
                    raise HTTPException(422, f"{where} {key!r} is given {count} times: give it once "
                                             f"({hints[key]})")
    return check
