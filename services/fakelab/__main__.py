from services.fakelab.main import main

raise SystemExit(main())
