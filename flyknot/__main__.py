from flyknot.cli import main

raise SystemExit(main())
