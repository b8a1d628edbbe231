import os

from hypothesis import settings

# CI runs the property tests on a fixed sequence of examples (derandomize) so that a
# rare random draw cannot turn a clean clone red; a developer's `make test` explores
# new random examples on every run. `.ci/run` selects the profile.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev", print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))


import logging  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _root_logging_as_it_was():
    """A command's ``main`` run in-process configures the root logger (``basicConfig``) with the
    stream pytest captures for that test; put the root logger back afterwards, so that a later
    test never logs into a closed stream ("--- Logging error ---")."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    for h in root.handlers[:]:
        if h not in handlers:
            root.removeHandler(h)
    root.setLevel(level)
