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
