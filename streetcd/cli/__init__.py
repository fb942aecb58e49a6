"""Thin command line over the library. Progress bars live here, never in the library."""
