"""Shared fixtures. Tests that need the original robots skip with a message when they are absent."""
from __future__ import annotations

import pytest

from mjx_morph.unimal.sets import unimals_root

NO_UNIMALS = ("the original robots (../shared/unimals_100 or $MJX_MORPH_UNIMALS) are not available; "
              "this test needs them")


@pytest.fixture(scope="session")
def unimals():
    root = unimals_root()
    if root is None:
        pytest.skip(NO_UNIMALS)
    return root
