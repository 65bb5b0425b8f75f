"""Ground truths as callers see them (the catalog) and their files, validated, kept and cached (the cache)."""
