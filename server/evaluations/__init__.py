"""Evaluations as callers see them: accepting and running one, its options, its uploads, comparisons."""
