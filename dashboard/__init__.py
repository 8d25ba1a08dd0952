"""The Viser web dashboard service."""
