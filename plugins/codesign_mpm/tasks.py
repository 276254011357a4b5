"""`codesign_mpm.tasks.register_task` and the task classes where plugins import them; the tasks
live in `codesign_mpm.environment.tasks`."""
from codesign_mpm.environment.tasks import *  # noqa: F401,F403
