"""``python -m flyknot_app``: the ``flyknot`` command line."""

from flyknot_app.cli import main

raise SystemExit(main())
