"""trueaxis.inspect (see DESIGN.md §2)."""
