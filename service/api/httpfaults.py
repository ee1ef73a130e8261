"""HTTP helpers: the complete ``Allow`` header of a 405."""

from __future__ import annotations

from typing import Any


def allowed_methods(routes: Any, scope: dict) -> str:
    """Every method some route accepts on this path (Starlette's 405 names only the first route's)."""
    from starlette.routing import Match

    methods: set[str] = set()
    probe = {**scope, "method": "GET"}
    for route in routes:
        match, _ = route.matches({**probe, "type": "http"})
        if match != Match.NONE and getattr(route, "methods", None):
            methods |= set(route.methods)
    if "GET" in methods:
        methods.add("HEAD")
    return ", ".join(sorted(methods))
