"""One module per ``decod`` verb (see ``decod_rs.cli``)."""
