"""codesign: co-design of soft robots' bodies and controllers.

The core package knows no physics. It defines the four component interfaces,
the plugin registry, recipes, the runner and tracking; environments and
learning components come from plugins. Importing it must stay cheap: no
Taichi, torch or wandb at import time.
"""

from codesign.errors import CodesignError, PluginError, RecipeError, RegistryError

__version__ = "0.1.0"

#: Entry-point group through which every plugin, first- or third-party, is found.
ENTRY_POINT_GROUP = "codesign.plugins"

__all__ = [
    "ENTRY_POINT_GROUP",
    "CodesignError",
    "PluginError",
    "RecipeError",
    "RegistryError",
    "__version__",
]
