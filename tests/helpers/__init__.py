"""Plain helpers shared by tests (writers, tiny models, hand-built tables), imported normally;
fixtures live in tests/fixtures and tests/conftest.py."""
