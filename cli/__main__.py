"""``python -m cli ...`` is ``tether ...`` (the launcher starts every process this way)."""

from cli.main import main

raise SystemExit(main())
