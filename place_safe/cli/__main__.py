"""``python -m place_safe.cli``: the place-safe command."""

from place_safe.cli.app import main

raise SystemExit(main())
