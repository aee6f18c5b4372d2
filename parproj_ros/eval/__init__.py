"""Evaluation: normalized pairs against truth, paper reproduction, reference-grid comparison."""
