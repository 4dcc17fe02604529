from visionpos.cli.main import main

raise SystemExit(main())
