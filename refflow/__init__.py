"""Neutral infrastructure shared by ``sim``, ``flow`` and ``analysis``.

Only file plumbing lives here (atomic writes, JSON sidecars, config hashing,
package versions): nothing that could let the measurement see the ground truth.
"""
