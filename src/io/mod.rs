//! Native log ingestion (issue 4).
