//! End-to-end tests of the whole chain (preprocessor, server, simulated
//! link, session, client) live in `tests/`; their shared helpers (the
//! in-process server, procedural databases, the independent horizon test)
//! are in `planet-testkit`'s `harness` module.
