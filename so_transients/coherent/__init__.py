"""The coherent search: ``transient_find``'s coherent mode, on arrays.

- :mod:`.config`: its settings (the coherent-mode keys of ``transient_find``)
- :mod:`.statistic`: the coherent statistic Z of one wafer crossing and its map
- :mod:`.vetoes`: which maxima of the map look like a source crossing (glitch vetoes)
- :mod:`.crossing_chi2`: the chi-squared test over detector groups
- :mod:`.sweep_stack`: one sky position's Z summed over several crossings
- :mod:`.joint`: both bands of a wafer together: the joint-band statistic J
- :mod:`.find`: the candidates of a group: maxima of Z (or J), vetoed, stacked

Imports from :mod:`so_transients.common` and :mod:`so_transients.detect`.
"""
