"""The Gymnasium ids' module as `gymnasium.make("codesign_mpm.gym:codesign/...")` names it; the
environments live in `codesign_mpm.environment.gym`. Importing either registers them."""
from codesign_mpm.environment.gym import *  # noqa: F401,F403
