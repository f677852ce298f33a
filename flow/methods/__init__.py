"""Displacement-measurement methods: the interface every method implements, the registry that
finds them by name, and the built-in methods, one module (or, with its own kernels, one
folder) each.

``base`` holds the base classes and ``@register``; ``params`` each method's declared
parameters; ``registry`` loads the built-in methods on first use (``klt``, ``opencv_dense``,
and ``deepflow/``: the paper's DeepMatching + DeepFlow with the member and region fits). A
new method is a module here that subclasses a base class and registers itself, named in the
registry's list of built-in modules. This file imports nothing, so that importing
:mod:`flow.methods.base` (or one method) does not load every method.
"""
