"""What the bot flies: the scan and the pollination visits, each planned (checked before
the bot moves) and flown by an executor that keeps one resumable flight journal."""
