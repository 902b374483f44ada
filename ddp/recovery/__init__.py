"""Built-in recovery parts: the registry imports every module here (each registers itself) on the kind's first lookup."""
