"""A map: the stored scans and their signatures (SQLite `database*`, Milvus
`milvus_*`), the indexes searched over them (`signature_index`, `index/`), the map's
side views, and the `Map` facade (`facade`) with its writing (`writing`) and
build-db's entry points (`build`).

Kept empty: storage modules import each other and the query stage, and a package
that imported the facade here would put them in a circle.
"""
