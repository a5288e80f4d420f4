"""``flyknot bench``: the speed figures, each measured in one run."""
