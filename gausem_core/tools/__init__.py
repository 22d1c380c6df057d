"""Command-line tools behind ``gausem`` sub-commands."""
