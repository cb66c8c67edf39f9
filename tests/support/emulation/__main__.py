"""``python -m support.emulation KIND``: run one emulated USB device (see
``serve``)."""

from .serve import main

raise SystemExit(main())
