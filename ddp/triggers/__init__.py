"""Built-in subtask-end triggers; every module here registers itself on import."""

from ddp._autoload import import_submodules

import_submodules(__name__, __path__)
