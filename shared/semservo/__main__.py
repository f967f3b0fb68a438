"""``python -m semservo`` is the ``semservo`` command."""

from semservo.cli import main

raise SystemExit(main())
