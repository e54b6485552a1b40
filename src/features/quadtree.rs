//! ORB-SLAM's quadtree distribution of corners over a level.
//!
//! The detection area is cut into about square initial nodes; every node with
//! more than one corner is split into four until there are at least as many
//! nodes as wanted features (or no node can be split). When the next round of
//! splits would overshoot, the most populated nodes are split first. Each final
//! node keeps its strongest corner, so textured regions cannot take every
//! feature.
//!
//! Corners are not copied: nodes own ranges of one index array, and a split
//! partitions its range in place, so no allocation happens per corner or node
//! once the scratch buffers have grown.

use super::fast::Corner;

#[derive(Debug, Clone, Copy)]
struct Node {
    x0: f32,
    y0: f32,
    x1: f32,
    y1: f32,
    start: u32,
    end: u32,
}

impl Node {
    fn count(&self) -> usize {
        (self.end - self.start) as usize
    }
    fn splittable(&self) -> bool {
        self.count() > 1 && (self.x1 - self.x0 >= 1.0 || self.y1 - self.y0 >= 1.0)
    }
}

/// Reusable buffers of [`distribute`].
#[derive(Debug, Default, Clone)]
pub struct QuadScratch {
    idx: Vec<u32>,
    tmp: Vec<u32>,
    nodes: Vec<Node>,
    next: Vec<Node>,
    order: Vec<(u32, u32)>,
}

/// Split `node` into its four children, partitioning its index range; the
/// non-empty children are appended to `out`.
fn split(
    node: &Node,
    corners: &[Corner],
    idx: &mut [u32],
    tmp: &mut Vec<u32>,
    out: &mut Vec<Node>,
) {
    let hx = ((node.x1 - node.x0) / 2.0).ceil();
    let hy = ((node.y1 - node.y0) / 2.0).ceil();
    let (mx, my) = (node.x0 + hx, node.y0 + hy);
    let range = &mut idx[node.start as usize..node.end as usize];
    let child = |i: u32| -> usize {
        let c = &corners[i as usize];
        ((c.x as f32 >= mx) as usize) | (((c.y as f32 >= my) as usize) << 1)
    };
    let mut counts = [0usize; 4];
    for &i in range.iter() {
        counts[child(i)] += 1;
    }
    let mut starts = [0usize; 4];
    for k in 1..4 {
        starts[k] = starts[k - 1] + counts[k - 1];
    }
    tmp.clear();
    tmp.resize(range.len(), 0);
    let mut fill = starts;
    for &i in range.iter() {
        let c = child(i);
        tmp[fill[c]] = i;
        fill[c] += 1;
    }
    range.copy_from_slice(tmp);
    let bounds = [
        (node.x0, node.y0, mx, my),
        (mx, node.y0, node.x1, my),
        (node.x0, my, mx, node.y1),
        (mx, my, node.x1, node.y1),
    ];
    for k in 0..4 {
        if counts[k] > 0 {
            let (x0, y0, x1, y1) = bounds[k];
            out.push(Node {
                x0,
                y0,
                x1,
                y1,
                start: node.start + starts[k] as u32,
                end: node.start + (starts[k] + counts[k]) as u32,
            });
        }
    }
}

/// Choose about `n` well-spread corners of the region `[x0, x1) x [y0, y1)`:
/// indices into `corners` are written to `selected` in ascending order.
pub fn distribute(
    corners: &[Corner],
    (x0, y0, x1, y1): (f32, f32, f32, f32),
    n: usize,
    scratch: &mut QuadScratch,
    selected: &mut Vec<u32>,
) {
    selected.clear();
    if corners.is_empty() || n == 0 || x1 <= x0 || y1 <= y0 {
        return;
    }
    let QuadScratch {
        idx,
        tmp,
        nodes,
        next,
        order,
    } = scratch;
    let (w, h) = (x1 - x0, y1 - y0);
    let n_ini = ((w / h).round() as usize).max(1);
    let hx = w / n_ini as f32;
    // Initial nodes: counting sort of the corners by column band.
    let band = |c: &Corner| (((c.x as f32 - x0) / hx).floor().max(0.0) as usize).min(n_ini - 1);
    let mut counts = vec![0u32; n_ini + 1];
    for c in corners {
        counts[band(c) + 1] += 1;
    }
    for k in 1..=n_ini {
        counts[k] += counts[k - 1];
    }
    idx.clear();
    idx.resize(corners.len(), 0);
    let mut fill = counts.clone();
    for (i, c) in corners.iter().enumerate() {
        let b = band(c);
        idx[fill[b] as usize] = i as u32;
        fill[b] += 1;
    }
    nodes.clear();
    for k in 0..n_ini {
        if counts[k + 1] > counts[k] {
            nodes.push(Node {
                x0: x0 + hx * k as f32,
                y0,
                x1: x0 + hx * (k + 1) as f32,
                y1,
                start: counts[k],
                end: counts[k + 1],
            });
        }
    }
    loop {
        let prev = nodes.len();
        next.clear();
        let mut n_expand = 0;
        for node in nodes.iter() {
            if node.splittable() {
                let before = next.len();
                split(node, corners, idx, tmp, next);
                n_expand += next[before..].iter().filter(|c| c.count() > 1).count();
            } else {
                next.push(*node);
            }
        }
        std::mem::swap(nodes, next);
        if nodes.len() >= n || nodes.len() == prev {
            break;
        }
        if nodes.len() + 3 * n_expand > n {
            // Last rounds: split the most populated nodes first until `n`.
            loop {
                let prev = nodes.len();
                order.clear();
                order.extend(
                    nodes
                        .iter()
                        .enumerate()
                        .filter(|(_, nd)| nd.splittable())
                        .map(|(i, nd)| (nd.count() as u32, i as u32)),
                );
                order.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
                let mut alive = nodes.len();
                next.clear();
                for &(_, i) in order.iter() {
                    let node = nodes[i as usize];
                    let before = next.len();
                    split(&node, corners, idx, tmp, next);
                    // Mark the parent as removed by emptying it.
                    nodes[i as usize].end = nodes[i as usize].start;
                    alive = alive + (next.len() - before) - 1;
                    if alive >= n {
                        break;
                    }
                }
                nodes.retain(|nd| nd.count() > 0);
                nodes.extend_from_slice(next);
                if nodes.len() >= n || nodes.len() == prev {
                    break;
                }
            }
            break;
        }
    }
    for node in nodes.iter() {
        let range = &idx[node.start as usize..node.end as usize];
        let mut best = range[0];
        for &i in &range[1..] {
            if corners[i as usize].score > corners[best as usize].score {
                best = i;
            }
        }
        selected.push(best);
    }
    selected.sort_unstable();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn corner(x: u32, y: u32, score: u8) -> Corner {
        Corner { x, y, score }
    }

    #[test]
    fn clustered_corners_do_not_take_every_feature() {
        // 400 strong corners packed in the top-left, 40 weak ones spread.
        let mut cs = Vec::new();
        for y in 0..20 {
            for x in 0..20 {
                cs.push(corner(20 + x, 20 + y, 100));
            }
        }
        for k in 0..40u32 {
            cs.push(corner(100 + (k % 8) * 60, 100 + (k / 8) * 70, 10));
        }
        let mut sel = Vec::new();
        distribute(
            &cs,
            (19.0, 19.0, 621.0, 461.0),
            60,
            &mut QuadScratch::default(),
            &mut sel,
        );
        assert!(sel.len() >= 60 && sel.len() <= 63, "{}", sel.len());
        let spread = sel.iter().filter(|&&i| i >= 400).count();
        assert_eq!(spread, 40, "every isolated corner is kept");
        // Each selected corner is unique and sorted.
        assert!(sel.windows(2).all(|w| w[0] < w[1]));
    }

    #[test]
    fn keeps_the_strongest_per_node() {
        let cs = vec![corner(30, 30, 5), corner(31, 30, 50), corner(300, 300, 7)];
        let mut sel = Vec::new();
        distribute(
            &cs,
            (19.0, 19.0, 621.0, 461.0),
            2,
            &mut QuadScratch::default(),
            &mut sel,
        );
        assert_eq!(sel, vec![1, 2]);
    }

    #[test]
    fn fewer_corners_than_wanted_keeps_all() {
        let cs: Vec<_> = (0..10).map(|k| corner(20 + 50 * k, 40, 20)).collect();
        let mut sel = Vec::new();
        distribute(
            &cs,
            (19.0, 19.0, 621.0, 461.0),
            100,
            &mut QuadScratch::default(),
            &mut sel,
        );
        assert_eq!(sel, (0..10).collect::<Vec<_>>());
        distribute(
            &[],
            (19.0, 19.0, 621.0, 461.0),
            100,
            &mut QuadScratch::default(),
            &mut sel,
        );
        assert!(sel.is_empty());
    }
}
