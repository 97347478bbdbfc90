"""Narrow observations: synchronised narrow images matched after a first adjustment, and adjusted again with them."""
