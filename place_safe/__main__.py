"""``python -m place_safe``: the place-safe command."""

from place_safe.cli.app import main

raise SystemExit(main())
