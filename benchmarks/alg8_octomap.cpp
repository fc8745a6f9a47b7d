// The thesis's merge loop (Jessup 2013, Alg. 8, Appendix A.3) on OctoMap 1.10, as the live peer of
// benchmarks/bench_fuse.py: for every leaf of M2 (OctoMap's leaf iterator), walk M1's tree from the
// root along the leaf's key down to the leaf's depth, then
//   case 1: the path leaves M1's known space -> create the node at M2's depth with M2's value;
//   case 2: M1's leaf has the same depth -> add M2's log-odds (clamped, updateNodeLogOdds);
//   case 3: M1's leaf is coarser -> expandNode() down to M2's depth (children inherit), add to the one;
//   case 4: M1 is finer -> add M2's log-odds to every leaf below, its unknown parts become leaves
//           with M2's value;
// then OcTree::prune(). A.3's bugs are not reproduced: the code sets M2's occupied leaves to
// p = 0.6 first and, where M2 is finer, stores logodds(p1 + p2) (probabilities added); A.3 also
// looks a node's depth up with one search per depth and only handles M2's leaf centre in case 4.
// This walks each M2 leaf once, which is as fast as the loop can be written on OctoMap's nodes.
//
// Input: a binary dump written by bench_fuse.py: two maps, each (int64 n, float64 resolution,
// uint16 min-corner keys [n][3], uint8 depths [n], float32 log-odds [n]), then float32 clamp
// min and max (log-odds). argv[2]: repeats (the trees are rebuilt, untimed, before every run);
// argv[3] (optional, "-" for none): write the merged leaves there (same per-map layout, min-corner
// keys); argv[4]: `morton` (default) or `shuffled`, the order the trees are built in (see build()).
// Output (stdout, last line): {"merge_s": median wall, "prune_s": median wall, "leaves": n, ...}.
//
// Build (done by bench_fuse.py when g++ and cmeel-octomap exist):
//   g++ -O3 -std=c++17 alg8_octomap.cpp -I$PREFIX/include -L$PREFIX/lib -loctomap -loctomath
#include <octomap/OcTree.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <numeric>
#include <random>
#include <string>
#include <vector>

using octomap::OcTree;
using octomap::OcTreeKey;
using octomap::OcTreeNode;

struct Leaves {
  int64_t n = 0;
  double res = 0;
  std::vector<uint16_t> keys;
  std::vector<uint8_t> depths;
  std::vector<float> log_odds;
};

static bool read_leaves(std::ifstream& in, Leaves& m) {
  in.read(reinterpret_cast<char*>(&m.n), 8);
  in.read(reinterpret_cast<char*>(&m.res), 8);
  if (!in || m.n < 0) return false;
  m.keys.resize(3 * m.n);
  m.depths.resize(m.n);
  m.log_odds.resize(m.n);
  in.read(reinterpret_cast<char*>(m.keys.data()), 6 * m.n);
  in.read(reinterpret_cast<char*>(m.depths.data()), m.n);
  in.read(reinterpret_cast<char*>(m.log_odds.data()), 4 * m.n);
  return bool(in);
}

class MergeTree : public OcTree {
 public:
  MergeTree(double res, float lmin, float lmax) : OcTree(res) {
    clamping_thres_min = lmin;
    clamping_thres_max = lmax;
  }
  long cases[4] = {0, 0, 0, 0};

  // a leaf at any depth, by walking down from the root (protected root access)
  void insertLeaf(const OcTreeKey& key, int depth, float log_odds) {
    OcTreeNode* node = ensureRoot();
    for (int d = 0; d < depth; ++d) {
      unsigned idx = octomap::computeChildIdx(key, 15 - d);
      node = nodeChildExists(node, idx) ? getNodeChild(node, idx) : createNodeChild(node, idx);
    }
    node->setLogOdds(log_odds);
  }

  void beginMerge() { root_is_leaf = root != nullptr && !nodeHasChildren(root); }

  // Alg. 8's body for one M2 leaf
  void mergeLeaf(const OcTreeKey& key, int depth, float v) {
    OcTreeNode* node = ensureRoot();
    for (int d = 0; d < depth; ++d) {
      if (!nodeHasChildren(node) && (d > 0 || root_is_leaf)) {  // case 3: M1's leaf is coarser
        expandNode(node);
        if (d == 0) root_is_leaf = false;
        ++cases[2];
      }
      unsigned idx = octomap::computeChildIdx(key, 15 - d);
      if (nodeChildExists(node, idx)) {
        node = getNodeChild(node, idx);
        continue;
      }
      for (; d < depth; ++d) node = createNodeChild(node, octomap::computeChildIdx(key, 15 - d));
      node->setLogOdds(clamp(v));  // case 1: unknown in M1
      ++cases[0];
      return;
    }
    if (!nodeHasChildren(node)) {
      updateNodeLogOdds(node, v);  // case 2 (or the end of case 3)
      ++cases[1];
    } else {
      addBelow(node, v);  // case 4
      ++cases[3];
    }
  }

  void write(const std::string& path) {
    std::vector<uint16_t> keys;
    std::vector<uint8_t> depths;
    std::vector<float> lo;
    for (auto it = begin_leafs(), end = end_leafs(); it != end; ++it) {
      unsigned d = it.getDepth();
      uint16_t mask = static_cast<uint16_t>(~((1u << (16 - d)) - 1u));  // centre key -> min corner
      OcTreeKey k = it.getKey();
      keys.insert(keys.end(), {uint16_t(k[0] & mask), uint16_t(k[1] & mask), uint16_t(k[2] & mask)});
      depths.push_back(static_cast<uint8_t>(d));
      lo.push_back(it->getLogOdds());
    }
    int64_t n = static_cast<int64_t>(depths.size());
    double res = getResolution();
    std::ofstream out(path, std::ios::binary);
    out.write(reinterpret_cast<const char*>(&n), 8);
    out.write(reinterpret_cast<const char*>(&res), 8);
    out.write(reinterpret_cast<const char*>(keys.data()), 6 * n);
    out.write(reinterpret_cast<const char*>(depths.data()), n);
    out.write(reinterpret_cast<const char*>(lo.data()), 4 * n);
  }

 private:
  bool root_is_leaf = false;

  OcTreeNode* ensureRoot() {
    if (!root) {
      root = new OcTreeNode();
      tree_size++;
    }
    return root;
  }

  float clamp(float v) const { return std::min(std::max(v, clamping_thres_min), clamping_thres_max); }

  void addBelow(OcTreeNode* node, float v) {
    for (unsigned i = 0; i < 8; ++i) {
      if (!nodeChildExists(node, i)) {
        createNodeChild(node, i)->setLogOdds(clamp(v));  // a part of M2's leaf M1 does not know
      } else {
        OcTreeNode* child = getNodeChild(node, i);
        if (nodeHasChildren(child)) addBelow(child, v);
        else updateNodeLogOdds(child, v);
      }
    }
  }
};

// Leaves inserted in Morton order (the node layout OcTree::read gives a .bt file) or, `shuffled`, in a
// random order: nodes scattered in memory, as in a map grown by scan insertion over a long run.
static void build(MergeTree& t, const Leaves& m, bool shuffled) {
  std::vector<int64_t> order(m.n);
  std::iota(order.begin(), order.end(), 0);
  if (shuffled) std::shuffle(order.begin(), order.end(), std::mt19937_64(1));
  for (int64_t i : order) {
    OcTreeKey k(m.keys[3 * i], m.keys[3 * i + 1], m.keys[3 * i + 2]);
    t.insertLeaf(k, m.depths[i], m.log_odds[i]);
  }
}

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: alg8_octomap dump.bin [repeats] [merged.bin|-] [morton|shuffled]\n";
    return 2;
  }
  std::ifstream in(argv[1], std::ios::binary);
  Leaves m1, m2;
  float clamp[2];
  if (!read_leaves(in, m1) || !read_leaves(in, m2) || !in.read(reinterpret_cast<char*>(clamp), 8)) {
    std::cerr << argv[1] << ": short read\n";
    return 1;
  }
  int repeats = argc > 2 ? std::max(1, std::atoi(argv[2])) : 1;
  bool write_out = argc > 3 && std::string(argv[3]) != "-";
  bool shuffled = argc > 4 && std::string(argv[4]) == "shuffled";
  std::vector<double> merge_s, prune_s;
  size_t leaves = 0;
  long cases[4] = {0, 0, 0, 0};
  for (int r = 0; r < repeats; ++r) {
    MergeTree t1(m1.res, clamp[0], clamp[1]);
    MergeTree t2(m2.res, clamp[0], clamp[1]);
    build(t1, m1, shuffled);
    build(t2, m2, shuffled);
    t1.beginMerge();
    auto t0 = std::chrono::steady_clock::now();
    for (auto it = t2.begin_leafs(), end = t2.end_leafs(); it != end; ++it)
      t1.mergeLeaf(it.getKey(), static_cast<int>(it.getDepth()), it->getLogOdds());
    auto t_merge = std::chrono::steady_clock::now();
    t1.prune();
    auto t_prune = std::chrono::steady_clock::now();
    merge_s.push_back(std::chrono::duration<double>(t_merge - t0).count());
    prune_s.push_back(std::chrono::duration<double>(t_prune - t_merge).count());
    leaves = t1.getNumLeafNodes();
    std::copy(t1.cases, t1.cases + 4, cases);
    if (r == repeats - 1 && write_out) t1.write(argv[3]);
  }
  std::sort(merge_s.begin(), merge_s.end());
  std::sort(prune_s.begin(), prune_s.end());
  std::printf("{\"merge_s\": %.5f, \"prune_s\": %.5f, \"leaves\": %zu, \"repeats\": %d, "
              "\"cases\": [%ld, %ld, %ld, %ld]}\n",
              merge_s[repeats / 2], prune_s[repeats / 2], leaves, repeats, cases[0], cases[1],
              cases[2], cases[3]);
  return 0;
}
