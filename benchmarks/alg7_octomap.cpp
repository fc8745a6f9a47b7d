// The thesis's map transformation (Jessup 2013, Alg. 4-7, Appendix A.2) on OctoMap 1.10, as the
// peer of benchmarks/bench_transform.py. The two bugs of A.2 that change the geometry are fixed
// (rotation row 3 uses element (2,1); inverse translation is -R^T t); otherwise it is A.2: a dense
// scan of the transformed bounding box at the finest resolution, the nearest source voxel must be
// known, 7 neighbour searches, unknown neighbours weigh as probability 0, then prune.
//
// Input: a binary dump written by bench_transform.py (int64 n, float64 resolution, uint16 keys
// [n][3], uint8 depths [n], float32 log-odds [n], float64 T_dst_src [4][4] row-major).
// Output (stdout, last line): {"seconds": wall, "cpu_seconds": process CPU, "scanned": voxels,
// "leaves": output leaves}.
//
// Build (done by bench_transform.py when g++ and cmeel-octomap exist):
//   g++ -O3 -std=c++17 alg7_octomap.cpp -I$PREFIX/include -L$PREFIX/lib -loctomap -loctomath
#include <octomap/OcTree.h>

#include <chrono>
#include <ctime>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <vector>

using octomap::OcTree;
using octomap::OcTreeKey;
using octomap::OcTreeNode;
using octomap::point3d;

// Leaves at any depth are inserted by walking down from the root (protected root access).
class BuildTree : public OcTree {
 public:
  explicit BuildTree(double res) : OcTree(res) {}
  void insertLeaf(const OcTreeKey& key, int depth, float log_odds) {
    if (!root) {
      root = new OcTreeNode();
      tree_size++;
    }
    OcTreeNode* node = root;
    for (int d = 0; d < depth; ++d) {
      unsigned idx = octomap::computeChildIdx(key, 15 - d);
      node = nodeChildExists(node, idx) ? getNodeChild(node, idx) : createNodeChild(node, idx);
    }
    node->setLogOdds(log_odds);
  }
};

static inline double sgn(double v) { return v < 0 ? -1.0 : 1.0; }

static double occ(OcTree& t, const point3d& p) {
  OcTreeNode* n = t.search(p);
  return n ? n->getOccupancy() : 0.0;
}

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: alg7_octomap dump.bin\n";
    return 2;
  }
  std::ifstream in(argv[1], std::ios::binary);
  int64_t n = 0;
  double res = 0;
  in.read(reinterpret_cast<char*>(&n), 8);
  in.read(reinterpret_cast<char*>(&res), 8);
  std::vector<uint16_t> keys(3 * n);
  std::vector<uint8_t> depths(n);
  std::vector<float> lo(n);
  double T[16];
  in.read(reinterpret_cast<char*>(keys.data()), 6 * n);
  in.read(reinterpret_cast<char*>(depths.data()), n);
  in.read(reinterpret_cast<char*>(lo.data()), 4 * n);
  in.read(reinterpret_cast<char*>(T), sizeof(T));
  if (!in) {
    std::cerr << "short read\n";
    return 1;
  }
  BuildTree tree(res);
  for (int64_t i = 0; i < n; ++i) {
    // keys are min-corner keys; OctoMap's child walk only reads the top `depth` bits
    OcTreeKey k(keys[3 * i], keys[3 * i + 1], keys[3 * i + 2]);
    tree.insertLeaf(k, depths[i], lo[i]);
  }
  tree.updateInnerOccupancy();

  auto t0 = std::chrono::steady_clock::now();
  std::clock_t cpu0 = std::clock();
  double R[3][3] = {{T[0], T[1], T[2]}, {T[4], T[5], T[6]}, {T[8], T[9], T[10]}};
  double t[3] = {T[3], T[7], T[11]};
  double Ri[3][3], ti[3];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) Ri[r][c] = R[c][r];
  for (int r = 0; r < 3; ++r) ti[r] = -(Ri[r][0] * t[0] + Ri[r][1] * t[1] + Ri[r][2] * t[2]);
  double minX, minY, minZ, maxX, maxY, maxZ;
  tree.getMetricMin(minX, minY, minZ);
  tree.getMetricMax(maxX, maxY, maxZ);
  double bmin[3] = {1e300, 1e300, 1e300}, bmax[3] = {-1e300, -1e300, -1e300};
  for (int c = 0; c < 8; ++c) {  // Alg. 4
    double p[3] = {(c & 1) ? maxX : minX, (c & 2) ? maxY : minY, (c & 4) ? maxZ : minZ};
    for (int r = 0; r < 3; ++r) {
      double v = R[r][0] * p[0] + R[r][1] * p[1] + R[r][2] * p[2] + t[r];
      bmin[r] = std::min(bmin[r], v);
      bmax[r] = std::max(bmax[r], v);
    }
  }
  OcTree out(res);
  long scanned = 0;
  for (double z = bmin[2] - res / 2; z < bmax[2] + res / 2; z += res) {  // Alg. 7
    for (double y = bmin[1] - res / 2; y < bmax[1] + res / 2; y += res) {
      for (double x = bmin[0] - res / 2; x < bmax[0] + res / 2; x += res) {
        ++scanned;
        point3d src(Ri[0][0] * x + Ri[0][1] * y + Ri[0][2] * z + ti[0],
                    Ri[1][0] * x + Ri[1][1] * y + Ri[1][2] * z + ti[1],
                    Ri[2][0] * x + Ri[2][1] * y + Ri[2][2] * z + ti[2]);
        OcTreeKey sk;
        if (!tree.coordToKeyChecked(src, sk)) continue;
        OcTreeNode* c000n = tree.search(sk);
        if (!c000n) continue;
        point3d nn = tree.keyToCoord(sk);
        double xd = (src.x() - nn.x()) / res, yd = (src.y() - nn.y()) / res,
               zd = (src.z() - nn.z()) / res;
        double sx = sgn(xd) * res, sy = sgn(yd) * res, sz = sgn(zd) * res;
        double c000 = c000n->getOccupancy();
        double c001 = occ(tree, nn + point3d(0, 0, sz)), c010 = occ(tree, nn + point3d(0, sy, 0));
        double c011 = occ(tree, nn + point3d(0, sy, sz)), c100 = occ(tree, nn + point3d(sx, 0, 0));
        double c101 = occ(tree, nn + point3d(sx, 0, sz)), c110 = occ(tree, nn + point3d(sx, sy, 0));
        double c111 = occ(tree, nn + point3d(sx, sy, sz));
        double ax = std::fabs(xd), ay = std::fabs(yd), az = std::fabs(zd);
        double c00 = (1 - ax) * c000 + ax * c100, c10 = (1 - ax) * c010 + ax * c110;
        double c01 = (1 - ax) * c001 + ax * c101, c11 = (1 - ax) * c011 + ax * c111;
        double c0 = (1 - ay) * c00 + ay * c10, c1 = (1 - ay) * c01 + ay * c11;
        double p = (1 - az) * c0 + az * c1;
        p = std::min(std::max(p, 1e-6), 1 - 1e-6);
        OcTreeKey dk = out.coordToKey(point3d(x, y, z));
        OcTreeNode* dn = out.updateNode(dk, true);
        dn->setLogOdds(octomap::logodds(p));
      }
    }
  }
  out.updateInnerOccupancy();
  out.prune();
  double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  double cpu = double(std::clock() - cpu0) / CLOCKS_PER_SEC;
  std::printf("{\"seconds\": %.4f, \"cpu_seconds\": %.4f, \"scanned\": %ld, \"leaves\": %zu}\n",
              secs, cpu, scanned, out.getNumLeafNodes());
  return 0;
}
