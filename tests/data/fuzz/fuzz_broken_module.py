"""A user's module that cannot be imported (a plant-file fuzz case)."""

raise ImportError("this plant needs the package 'coolprop', which is not installed")
