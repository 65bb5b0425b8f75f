"""Who may see and do what: the policy (the one place that decides), the door that asks it before a route runs,
the routes' access dependencies, the accounts (users, projects, tokens, sessions), the audit log and the
headers every response carries."""
