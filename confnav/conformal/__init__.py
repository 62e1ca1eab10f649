"""The conformal solver: free space of a polygonal workspace onto a circle domain.

Graded boundary meshes (``boundary``, ``meshing``), Cauchy sums (``cauchy``), the generalized
Neumann kernel integral equation (``gnk``), disk maps of one curve (``diskmap``), the Koebe-type
iteration (``circledomain``), refinement with an error budget (``solver``), the solved map
(``cmap``) and its fast evaluation (``expansion``). Pure numerics: no Zenoh, no I/O.
"""
