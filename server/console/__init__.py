"""The organizers' console: the admin home, a challenge's settings, the accounts, the audit
records (docs/organizers.md, The console). Its own floor, above the domains it brings together
(docs/server.md, Inside the server): disabling an account also cancels its submissions."""
