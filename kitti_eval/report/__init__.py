"""Writing results: OpenPCDet's table, the JSON document, Markdown, precision-recall plots."""
