//! (extraction, issue 2: filled by the extraction work)
