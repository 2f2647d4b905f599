"""Language: the label sets (vocabularies), the text encoders of each feature space and text queries over a run's
instances."""
