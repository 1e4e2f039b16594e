"""trueaxis.sim (see DESIGN.md §2)."""
