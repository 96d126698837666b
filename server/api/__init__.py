"""The HTTP surface: routes, schemas, auth, uploads and the warm query cache (INTERFACES.md §4)."""
