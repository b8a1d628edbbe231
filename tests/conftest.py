import os

from hypothesis import settings

# CI runs the property tests on a fixed sequence of examples (derandomize) so that a
# rare random draw cannot turn a clean clone red; a developer's `make test` explores
# new random examples on every run. `.ci/run` selects the profile.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev", print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))
