"""Import-only stand-in (see __init__.py)."""
constexpr = object
