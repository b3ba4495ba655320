"""What a participant installs, served by the service itself: the SDK and the slim CLI as
wheels, and the policy template (docs/getting-started.md)."""
