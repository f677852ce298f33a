"""The default method, ``deepflow``, with its own kernels (numba).

``method`` registers ``deepflow``, ``deepflow-dense`` and ``deepmatching`` and runs them
against the reference frame: ``deepmatching`` (Revaud et al. 2016) gives the large
displacements, ``variational`` (DeepFlow, Weinzaepfel et al. 2013) refines them, ``member``
fits a beam's kinematics to the mask's outline and ``regionfit`` an affine warp to a textured
region, whichever the images support; ``checks`` validates the kernels' arrays before numba
sees them. This file imports nothing.
"""
