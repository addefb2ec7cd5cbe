"""Reading and writing simulated TOD, and the sotodlib obs loader for them.

- :mod:`.tod_file`: one HDF5 file per observation and detset
- :mod:`.loader`: the ``so_transients`` obs loader (registered when the package is imported)
"""
