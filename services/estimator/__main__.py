from services.estimator.main import main

raise SystemExit(main())
