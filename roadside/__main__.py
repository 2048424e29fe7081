from roadside.cli import main

raise SystemExit(main())
