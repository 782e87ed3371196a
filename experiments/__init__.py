"""Research experiments: what they showed and where it is written up, experiments/README.md."""
