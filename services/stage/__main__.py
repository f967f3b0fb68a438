from services.stage.main import main

raise SystemExit(main())
