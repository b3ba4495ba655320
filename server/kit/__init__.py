"""What every domain of the server shares: settings, the database, errors, request plumbing,
rate limits, secrets, monitoring, the page kit and the common schema bits."""
