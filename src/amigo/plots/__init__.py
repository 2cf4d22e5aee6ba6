"""Figures a user can look at (matplotlib, Agg backend; functions return figures)."""
