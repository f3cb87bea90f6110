import sys, random
n=int(sys.argv[1]); out=sys.argv[2]
random.seed(1)
L=0.001
h=[[1e-6*random.random() for j in range(n+1)] for i in range(n+1)]
def p(i,j): return (-L/2+L*i/n, -L/2+L*j/n, h[i][j])
with open(out,'w') as f:
    f.write('solid s\n')
    for i in range(n):
        for j in range(n):
            for t in ((p(i,j),p(i+1,j),p(i+1,j+1)),(p(i,j),p(i+1,j+1),p(i,j+1))):
                f.write(' facet normal 0 0 1\n  outer loop\n')
                for v in t: f.write('   vertex %.9e %.9e %.9e\n'%v)
                f.write('  endloop\n endfacet\n')
    f.write('endsolid s\n')
