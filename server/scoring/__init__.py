"""What a file goes through to be scored, for users' evaluations and benchmark submissions alike:
:mod:`.uploads` (a file kept as bytes: counted, hashed, named; read by the library's ``read_upload``; the ground
truths' files too) and :mod:`.evaluator` (a request's options, the evaluation's document, a sealed ground truth's
withheld details, the frame listing, the labels)."""
