from flyknot_app.cli import main

raise SystemExit(main())
