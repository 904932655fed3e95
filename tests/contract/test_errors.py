"""QueryError and the problem titles: one refusal type with its HTTP status and problem code."""

from __future__ import annotations

import pytest

from collider_contract import TITLES, QueryError, unknown_model


def test_the_titles_are_the_services_problem_titles():
    assert TITLES == {
        400: "Malformed request", 401: "Unauthorized", 403: "Forbidden", 404: "Not found",
        405: "Method not allowed", 408: "Request timeout", 409: "Conflict",
        413: "Request too large", 415: "Unsupported media type", 422: "Invalid request",
        429: "Too many requests", 499: "Client closed request", 500: "Internal server error",
        503: "Service unavailable", 504: "Deadline exceeded",
    }


def test_a_refusal_is_a_value_error_422_invalid_request_by_default():
    error = QueryError("points row 3 is bad")
    assert isinstance(error, ValueError)
    assert str(error) == error.detail == "points row 3 is bad"
    assert error.args == ("points row 3 is bad",)
    assert (error.status, error.code, error.title) == (422, "invalid-request", "Invalid request")


@pytest.mark.parametrize("status, title", [(413, "Request too large"), (404, "Not found"),
                                           (418, "Error"), (599, "Error")])
def test_the_title_follows_the_status(status, title):
    error = QueryError("too big", status=status, code="too-many-points")
    assert (error.detail, error.status, error.code, error.title) == ("too big", status,
                                                                     "too-many-points", title)


def test_an_unknown_model_is_a_404_listing_the_known_names_sorted():
    error = unknown_model("teapot", {"spot", "bunny", "dragon"})
    assert isinstance(error, QueryError)
    assert str(error) == "no model named 'teapot' (models: bunny, dragon, spot)"
    assert (error.status, error.code, error.title) == (404, "unknown-model", "Not found")
    assert str(unknown_model("x", [])) == "no model named 'x' (models: none)"
