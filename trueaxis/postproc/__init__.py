"""trueaxis.postproc (see DESIGN.md §2)."""
