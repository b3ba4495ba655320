"""Accounts: registration, password login, browser sessions and API tokens."""
