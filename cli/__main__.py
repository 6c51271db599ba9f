"""``python -m cli ...`` is ``tether ...`` (the launcher starts every process this way)."""

from cli.entry import main

raise SystemExit(main())
