"""Beyond one AP table: gates, comparisons and the paired bootstrap, per-frame diagnostics, one frame
inspected, many checkpoints at once."""
