"""The registry's tables replaced by copies of themselves, so what a test declares or registers is gone after it."""

from __future__ import annotations

import pytest
from geoloc import registry


def registry_copied(mp: pytest.MonkeyPatch) -> None:
    """Set the registry's tables to copies through `mp`; undoing `mp` brings back the tables as they were."""
    mp.setattr(registry, "_kinds", dict(registry._kinds))
    mp.setattr(registry, "_registry", {kind: dict(entries) for kind, entries in registry._registry.items()})
    mp.setattr(registry, "_loaded", set(registry._loaded))
