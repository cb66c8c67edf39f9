"""``python -m burrforce.server.devices.emulation KIND``: run one emulated USB device (see
``serve``)."""

from .serve import main

raise SystemExit(main())
