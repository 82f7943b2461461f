from hmdrt.cli import main

raise SystemExit(main())
