"""``python -m export``: the exporter's command-line interface (one module per sub-command)."""
