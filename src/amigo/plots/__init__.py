"""Figures a user can look at (matplotlib, Agg backend; functions return figures)."""

import logging

# Mathtext asks for TeX fonts that a minimal system may lack; matplotlib then logs one
# "findfont" warning per font and falls back to DejaVu Sans, which renders the figures
# correctly. Those lines would drown the commands' progress output.
logging.getLogger("matplotlib.font_manager").setLevel(logging.ERROR)
