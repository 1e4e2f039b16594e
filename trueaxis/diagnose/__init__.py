"""trueaxis.diagnose (see DESIGN.md §2)."""
