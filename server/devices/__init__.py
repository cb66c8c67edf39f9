"""Local haptic devices and vibration actuators, driven from a session.

- ``base``: what a device is (``HapticDevice``, ``DeviceInfo``, ``DeviceState``) and its errors.
- ``sim``, ``falcon``, ``vendor``: the back-ends; ``registry``: by name, with their options.
- ``render``: the coupling model re-rendered at the servo rate, with the watchdog (SPEC 7.5).
- ``mapping``: where the device's workspace lies in the bone.
- ``loop``, ``process``, ``stats``: the device loop, its process and its statistics.
- ``actuators``: vibration cues synthesized from the replies' parameters.
- ``discovery``, ``udev``: what is plugged in, and the rules Linux needs to open it.
- ``selftest``: ``burrforce device test``.

USB devices emulated with umockdev, for the tests and the project's benchmarks, are the
checkout's harness (``tests/support/emulation``), not part of this package.
"""
