"""Data: adapters, the compact scene format, catalogs, windows."""
