"""Who may do what: scopes and roles, passwords (Argon2, PAM), tokens and keys, the login
throttle, the operator lock and the audit trail. The API's route table says which scope each
route needs (:mod:`backend.api.access`)."""
