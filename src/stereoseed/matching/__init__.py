"""Sparse matching of interest points between two images (paper §4.1 steps 3-4, §4.2).

One module per job; import each name from the module that defines it (nothing is re-exported):

* :mod:`.containers` -- the result containers :class:`Matches`, :class:`Alignment`, :class:`PairMatches`;
* :mod:`.zncc` -- ZNCC scores, candidate masks, mutual best and uniqueness: :func:`match_zncc`;
  its Numba kernels live in :mod:`.zncc_kernels`;
* :mod:`.alignment` -- affine patch alignment (:func:`align_matches`), the localisation check
  (:func:`filter_localization`), sub-pixel refinement (:func:`refine_features`), :class:`PairCache`;
  its Numba kernels live in :mod:`.alignment_kernel`;
* :mod:`.two_view` -- epipolar geometry: band mask and filter, robust F;
* :mod:`.pair` -- the pair recipe the pipeline calls: :func:`match_pair`.

Every threshold is a field of :class:`stereoseed.config.MatchingConfig`; the recipe and what each
of its additions was measured to give is described in docs/matching.md.
"""
