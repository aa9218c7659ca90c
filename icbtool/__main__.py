from icbtool.cli import main

raise SystemExit(main())
