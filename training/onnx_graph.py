"""Rewrites of an exported RoadSegNet graph that onnxruntime runs faster, and their inverse for
loading the weights back (onnx only, no torch).

A decoder block reads the concatenation of the upsampled deeper features and the skip:
Concat -> depthwise Conv -> Relu -> 1x1 Conv -> Relu. A depthwise convolution treats every
channel alone and a 1x1 convolution is a sum over its input channels, so the block is, without
the concatenation, each input through its own share of the depthwise kernels and of the 1x1
weights, the two sums added (the bias once): the same function. The concatenation copied the
largest tensors of the network (48 channels at 1/2 resolution) and onnxruntime fuses the Add
into the second 1x1 convolution: at 640x312 on one thread, 8.3 -> 6.9 ms a frame, labels
unchanged (2026-11-25, 500 benchmark frames)."""

import numpy as np

SPLIT = "/split"  # node names of a split block: <Concat's name>/split<k>/dw | pw | relu


def split_concatenations(proto) -> int:
    """Rewrite, in place, every Concat -> depthwise Conv -> Relu -> 1x1 Conv -> Relu of `proto`
    as one depthwise Conv -> Relu -> 1x1 Conv per Concat input, summed by Add before the last
    Relu. -> how many blocks were rewritten."""
    from onnx import helper, numpy_helper

    graph = proto.graph
    tensors = {t.name: t for t in graph.initializer}
    # one list of the node objects, so that the id()s the rewrite is keyed on stay theirs
    nodes = list(graph.node)
    consumers: dict[str, list] = {}
    for node in nodes:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    producer = {out: node for node in nodes for out in node.output}

    def array(name):
        return numpy_helper.to_array(tensors[name])

    def only_consumer(name, op_type):
        users = consumers.get(name, [])
        return users[0] if len(users) == 1 and users[0].op_type == op_type else None

    def channels(name):  # the output channels of the Conv that (through Resize, Relu) made it
        node = producer.get(name)
        while node is not None and node.op_type != "Conv":
            node = producer.get(node.input[0])
        return None if node is None else int(tensors[node.input[1]].dims[0])

    replaced, added, weights = set(), {}, []
    for cat in [n for n in nodes if n.op_type == "Concat"]:
        dw = only_consumer(cat.output[0], "Conv")
        attrs = {} if dw is None else {a.name: helper.get_attribute_value(a) for a in dw.attribute}
        relu = dw and only_consumer(dw.output[0], "Relu")
        pw = relu and only_consumer(relu.output[0], "Conv")
        if (pw is None or attrs.get("group", 1) == 1 or len(dw.input) < 3 or len(pw.input) < 3
                or any(i not in tensors for i in (*dw.input[1:], *pw.input[1:]))
                or list(tensors[pw.input[1]].dims[2:]) != [1, 1]):
            continue
        sizes = [channels(name) for name in cat.input]
        w_dw, b_dw, w_pw = array(dw.input[1]), array(dw.input[2]), array(pw.input[1])
        if None in sizes or not sum(sizes) == len(w_dw) == attrs["group"]:
            continue
        new, sums, start = [], [], 0
        for k, (name, size) in enumerate(zip(cat.input, sizes, strict=True)):
            part, prefix = slice(start, start + size), f"{cat.name}{SPLIT}{k}"
            start += size
            for suffix, value in (("dw_w", w_dw[part]), ("dw_b", b_dw[part]),
                                  ("pw_w", w_pw[:, part])):
                weights.append(numpy_helper.from_array(np.ascontiguousarray(value),
                                                       f"{prefix}/{suffix}"))
            new.append(helper.make_node("Conv", [name, f"{prefix}/dw_w", f"{prefix}/dw_b"],
                                          [f"{prefix}/dw"], name=f"{prefix}/dw",
                                          **{**attrs, "group": size}))
            new.append(helper.make_node("Relu", [f"{prefix}/dw"], [f"{prefix}/relu"],
                                          name=f"{prefix}/relu"))
            bias = [pw.input[2]] if k == 0 else []
            new.append(helper.make_node("Conv", [f"{prefix}/relu", f"{prefix}/pw_w", *bias],
                                          [f"{prefix}/pw"], name=f"{prefix}/pw"))
            sums.append(f"{prefix}/pw")
        total = sums[0]
        for k, part in enumerate(sums[1:], 1):
            out = pw.output[0] if k == len(sums) - 1 else f"{cat.name}{SPLIT}/sum{k}"
            new.append(helper.make_node("Add", [total, part], [out], name=out))
            total = out
        replaced |= {id(cat), id(dw), id(relu), id(pw)}
        added[id(cat)] = new
    if not added:
        return 0
    kept = []
    for node in nodes:  # the new nodes where their Concat was: still in execution order
        kept.extend(added.get(id(node), []) if id(node) in replaced else [node])
    used = {name for node in kept for name in node.input}
    del graph.node[:]
    graph.node.extend(kept)
    old = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(old + weights)
    return len(added)


def merged_convolutions(proto, tensors: dict) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
    """(name, weight, bias or None) of each Conv of `proto` in execution order, with the blocks
    split_concatenations split merged back into their depthwise and their 1x1 convolution.
    `tensors`: initializer name -> array."""
    convs, seen = [], set()
    nodes = [n for n in proto.graph.node if n.op_type == "Conv"]
    for node in nodes:
        if SPLIT not in node.name:
            convs.append((node.name, tensors[node.input[1]],
                          tensors[node.input[2]] if len(node.input) > 2 else None))
            continue
        block = node.name.rsplit(SPLIT, 1)[0]
        if block in seen:
            continue
        seen.add(block)
        parts = sorted((n for n in nodes if n.name.rsplit(SPLIT, 1)[0] == block),
                       key=lambda n: n.name)
        dws = [n for n in parts if n.name.endswith("/dw")]
        pws = [n for n in parts if n.name.endswith("/pw")]
        convs.append((f"{block}/dw", np.concatenate([tensors[n.input[1]] for n in dws]),
                      np.concatenate([tensors[n.input[2]] for n in dws])))
        convs.append((f"{block}/pw", np.concatenate([tensors[n.input[1]] for n in pws], axis=1),
                      tensors[pws[0].input[2]]))
    return convs


RESIZE_MATMUL = "/as_matmul"  # node names of a rewritten Resize: <Resize's name>/as_matmul/...


def resizes_as_matmuls(proto, first: int = 1) -> int:
    """Rewrite, in place, the first `first` linear half-pixel Resizes given `sizes` (in
    execution order: the deepest features' first) as two matrix products, out = A_h @ x @
    A_w^T, rows first; each A (out, in) holds the interpolation's weights max(0, 1 - |src(y)
    - i|) at source coordinate src(y) = clip((y + 0.5) / (out / in) - 0.5, 0, in - 1), built
    in the graph from the shapes (onnxruntime folds them to constants once it knows the input
    height). -> how many were rewritten.

    The packaged network's deepest Resize goes from the 1/16 grid to the 1/8 grid, whose rows
    are odd at every height the runtime runs (360 less whole 16-row steps, so 248 rows: 16 ->
    31), so its scale is no integer and onnxruntime runs it outside its blocked layout with its
    generic kernel: 1.2 ms of the network's 11.5 at 248 rows on one thread. With the products
    instead the network runs 1.06-1.10x as fast (0.7-1.0 ms a frame, 2026-12-02), the same
    function up to float rounding (logits within 5e-5 of the Resize's; no coarse argmax
    changed on 40 held-out frames). The 2x Resizes, which onnxruntime runs blocked, stay. The
    packaged file is its export rewritten so (`python -m training.onnx_graph FILE`);
    export_onnx does not apply it."""
    from onnx import TensorProto, helper, numpy_helper

    graph = proto.graph
    nodes = list(graph.node)
    targets = [n for n in nodes if n.op_type == "Resize" and len(n.input) == 4 and n.input[3]
               and _attrs(n).get("mode") == b"linear"
               and _attrs(n).get("coordinate_transformation_mode") == b"half_pixel"][:first]
    if not targets:
        return 0
    consts = {"zero": 0.0, "half": 0.5, "one": 1.0}
    graph.initializer.extend(numpy_helper.from_array(np.array(v, np.float32),
                                                     f"{RESIZE_MATMUL}/{k}")
                             for k, v in consts.items())
    for axis in (2, 3):
        for k, v in (("start", axis), ("end", axis + 1)):
            graph.initializer.append(numpy_helper.from_array(np.array([v], np.int64),
                                                             f"{RESIZE_MATMUL}/{k}{axis}"))
    graph.initializer.extend(numpy_helper.from_array(np.array([k], np.int64),
                                                     f"{RESIZE_MATMUL}/axis{k}") for k in (0, 1))
    added = {}
    for node in targets:
        x, sizes = node.input[0], node.input[3]
        name = f"{node.name}{RESIZE_MATMUL}"
        new = [helper.make_node("Shape", [x], [f"{name}/shape"], name=f"{name}/shape")]
        a_h = _interpolation(new, helper, TensorProto, name, f"{name}/shape", sizes, 2)
        a_w = _interpolation(new, helper, TensorProto, name, f"{name}/shape", sizes, 3)
        new += [helper.make_node("Transpose", [a_w], [f"{name}/a_w_t"], perm=[1, 0],
                                 name=f"{name}/a_w_t"),
                helper.make_node("MatMul", [a_h, x], [f"{name}/rows"],
                                 name=f"{name}/rows"),
                helper.make_node("MatMul", [f"{name}/rows", f"{name}/a_w_t"], [node.output[0]],
                                 name=f"{name}/cols")]
        added[id(node)] = new
    kept = []
    for node in nodes:  # the products where their Resize was: still in execution order
        kept.extend(added.get(id(node), [node]))
    del graph.node[:]
    graph.node.extend(kept)
    return len(added)


def _attrs(node) -> dict:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _interpolation(new: list, helper, TensorProto, name: str, shape: str, sizes: str,
                   axis: int) -> str:
    """Append to `new` the nodes of the (out, in) linear half-pixel interpolation weights
    along `axis` (resizes_as_matmuls); -> the name of the matrix."""
    c = f"{RESIZE_MATMUL}/"
    p = f"{name}/{axis}/"

    def op(kind, inputs, out, **kw):
        new.append(helper.make_node(kind, inputs, [p + out], name=p + out, **kw))
        return p + out

    n_in = op("Cast", [op("Slice", [shape, f"{c}start{axis}", f"{c}end{axis}"], "in_i")],
              "in", to=TensorProto.FLOAT)
    n_out = op("Cast", [op("Slice", [sizes, f"{c}start{axis}", f"{c}end{axis}"], "out_i")],
               "out", to=TensorProto.FLOAT)
    scale = op("Div", [n_out, n_in], "scale")  # as onnxruntime's Resize: out / in
    ys = op("Range", [c + "zero", op("Squeeze", [n_out, c + "axis0"], "out_s"), c + "one"], "y")
    src = op("Sub", [op("Div", [op("Add", [ys, c + "half"], "yh"), scale], "ys"), c + "half"],
             "src_raw")
    last = op("Squeeze", [op("Sub", [n_in, c + "one"], "last1"), c + "axis0"], "last")
    src = op("Clip", [src, c + "zero", last], "src")
    ins = op("Range", [c + "zero", op("Squeeze", [n_in, c + "axis0"], "in_s"), c + "one"], "i")
    dist = op("Abs", [op("Sub", [op("Unsqueeze", [src, c + "axis1"], "src_col"),
                                 op("Unsqueeze", [ins, c + "axis0"], "i_row")], "diff")], "dist")
    return op("Relu", [op("Sub", [c + "one", dist], "hat")], "weights")


def main(argv: list[str] | None = None) -> int:
    """python -m training.onnx_graph FILE [OUT]: FILE (an export) with its deepest Resize as
    matrix products (resizes_as_matmuls), written to OUT (default: FILE in place); the same
    bytes every time for the same FILE."""
    import argparse

    import onnx

    parser = argparse.ArgumentParser(prog="python -m training.onnx_graph",
                                     description=main.__doc__.splitlines()[0])
    parser.add_argument("file")
    parser.add_argument("out", nargs="?")
    args = parser.parse_args(argv)
    proto = onnx.load(args.file)
    if any(RESIZE_MATMUL in n.name for n in proto.graph.node):
        raise SystemExit(f"{args.file}: its Resize is already rewritten")
    if not resizes_as_matmuls(proto):
        raise SystemExit(f"{args.file}: no linear half-pixel Resize with sizes to rewrite")
    onnx.checker.check_model(proto)
    onnx.save(proto, args.out or args.file)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
