//! Integration test helpers.
//!
//! The end-to-end tests themselves live in `tests/tests/`; this library only gives the
//! package a crate root, so it carries no items of its own.
#![deny(missing_docs)]
