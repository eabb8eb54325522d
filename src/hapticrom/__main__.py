from hapticrom.cli import main

raise SystemExit(main())
