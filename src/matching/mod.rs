//! Matching engine (issue 5).
