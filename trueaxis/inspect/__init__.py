"""trueaxis.inspect (layer 5, docs/architecture.md): CMM clouds against the CAD: clouds, deviations, form, tolerances,
reports."""
