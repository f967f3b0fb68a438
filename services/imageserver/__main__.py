from services.imageserver.main import main

raise SystemExit(main())
