"""Allow ``python -m app`` as an alias of the ``lasercal`` command."""

from app.cli import main

raise SystemExit(main())
