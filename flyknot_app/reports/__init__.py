"""What a run leaves for people: reports, figures, the results table, comparisons."""
