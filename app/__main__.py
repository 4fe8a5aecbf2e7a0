from calibcoach.app.cli import main

raise SystemExit(main())
