"""The settings of `POST /localize`, as the request sends them: form fields or query parameters, each once.

QueryForm is the Pydantic model FastAPI reads both from (the text as sent; the descriptions are query.py's, and
/openapi.json shows them); `sent_settings` joins the two, and the localizer's `parse` parses them, once, into the
QuerySettings everything below the door trusts.
"""

from __future__ import annotations

from fastapi import HTTPException
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
