"""regtree.registration: non-rigid registration of 2D shape collections.

A pure numpy/scipy implementation of Du et al. 2016, "Robust non-rigid point set
registration via building tree dynamically": affine ICP with bidirectional distance
(eqs. 2-9) as the similarity, CPD non-rigid registration (Myronenko & Song 2010), the
registration error of eq. 10, the dynamic tree of section 3.3, and the baselines it is
compared against (direct CPD and the static tree).
"""
