"""Exception types for mistakes a user can fix (bad recipe, unknown name).

The CLI prints these as one clear message without a traceback; any other
exception is treated as a bug and shown in full.
"""


class CodesignError(Exception):
    """Base of all user-facing errors."""


class RegistryError(CodesignError):
    """An unknown kind or name was requested, or a name was registered twice."""


class RecipeError(CodesignError):
    """A recipe could not be loaded, composed or validated."""


class PluginError(CodesignError):
    """A plugin could not be loaded."""


class DesignError(CodesignError):
    """A design leaves nothing the environment can simulate (empty, or every part too thin);
    optimizers rank such a design last, an episode of it is not played."""
