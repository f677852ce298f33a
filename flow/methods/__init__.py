"""Built-in displacement-measurement methods, one module each.

:mod:`flow.registry` loads them on first use. This file imports nothing, so that importing
:mod:`flow.methods.base` (or one method) does not load every method.
"""
