from visionpos.cli import main

raise SystemExit(main())
