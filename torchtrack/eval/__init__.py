"""Running trackers over many sequences or videos and scoring them: metrics, the evaluation
runner, corpus runs (one output set per video, resumable), the local / Ray backends both use,
reports and plots."""
