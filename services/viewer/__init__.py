"""`roadmap viewer`: a local web page of the merged map (the paper's colours, decoded from the
tiles), updated live from tile updates, with the localizers' poses; its HTML, JS and CSS are
files of this package (static/), served by the standard library, no internet needed."""
