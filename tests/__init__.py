"""The test suite, in folders that mirror the package's subpackages."""
