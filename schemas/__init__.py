"""octolog message contract: our .msg types, the CDR codec over rosbags, topic names."""
